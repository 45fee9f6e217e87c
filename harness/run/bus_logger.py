"""Records every frame on the bus into a log file (.blf or .asc) from the harness process."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can

from can_db.bus import BusDisconnected, open_bus
from can_db.codec import Codec, Decoded
from can_db.rt import FIFO_PRIORITY, make_realtime

FLUSH_EVERY_S = 0.2  # BLF container flush: bounds what a SIGKILL of the harness can lose


class BusRecorder:
    """A bus client in a background thread writing every received frame with can.Logger.

    It also follows the plant's SYNC frames (``sim_time_s``) so the harness can time its
    process-level faults in simulated seconds, and survives a bus-server restart.
    """

    def __init__(self, spec: str, path: Path, reconnect_s: float = 10.0,
                 rt: bool = False) -> None:
        self.path = path
        self.rt = rt  # the recording thread asks for SCHED_FIFO below the loop's processes
        self.bus = open_bus(spec, reconnect_s=reconnect_s)
        self.frames = 0
        self.sim_time_s = 0.0
        self.error: str | None = None
        self._codec = Codec()
        self._sync_id = self._codec.messages["SYNC"].frame_id
        self._stop = threading.Event()
        self._writer = can.Logger(str(path))
        self._thread = threading.Thread(target=self._run, name="bus-recorder", daemon=True)

    def start(self) -> BusRecorder:
        self._thread.start()
        return self

    def _run(self) -> None:
        if self.rt:
            make_realtime("bus-recorder", priority=FIFO_PRIORITY - 10)
        flush = getattr(self._writer, "_flush", None)  # BLF: write the open container
        last_flush = time.monotonic()
        try:
            while not self._stop.is_set():
                msg = self.bus.recv(timeout=0.1)
                if msg is not None:
                    self._writer.on_message_received(msg)
                    self.frames += 1
                    if msg.arbitration_id == self._sync_id:
                        sync = self._codec.decode_message(msg)
                        if isinstance(sync, Decoded):
                            self.sim_time_s = sync.values["SIM_TIME"]
                if flush is not None and time.monotonic() - last_flush > FLUSH_EVERY_S:
                    flush()
                    self._writer.file.flush()
                    last_flush = time.monotonic()
        except BusDisconnected as exc:
            self.error = str(exc)

    def drain(self, idle_s: float = 0.3) -> None:
        """Wait until no frame arrived for ``idle_s`` (the last answers are in the log)."""
        last, waited = -1, 0.0
        while waited < 5.0:
            if self.frames == last:
                break
            last = self.frames
            self._stop.wait(idle_s)
            waited += idle_s

    def stop(self) -> None:
        """Stop recording and close the file (BLF needs its footer to be complete)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._writer.stop()
        self.bus.shutdown()
