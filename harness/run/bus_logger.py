"""Records every frame on the bus into a log file (BLF, ASC or MF4) from the harness process.

Time stamps. In **lockstep** the plant runs faster than real time, so a wall-clock stamp
would squeeze 10 ms cycles into ~1 ms and CAN tools (CANalyzer, asammdf) would report cycle
time violations. The recorder therefore stamps each frame with **simulated time**: the j-th
frame of cycle k (plant burst, SYNC k, then the controller's answers, in bus order) gets
SYNC k's SIM_TIME + j × 250 µs (about one 8-byte classic frame at 500 kbit/s), so every
message keeps its exact 10 ms cycle and the log is the same for the same run (controller
frames go to the cycle their ECHO_CYCLE names). Wall-clock turnaround in lockstep is in
``controller_timing.csv``, not in the log. A plant restart (SIM_TIME going back) continues
the time line after the last cycle instead of stepping back. In **realtime** the frames keep
their receive time (wall clock). The log's own start time is the wall-clock start of the run;
the time base is written into the file: a marker/comment event at its start (BLF global
marker, ASC comment) and the MDF header comment (MF4), and is :attr:`BusRecorder.time_base`
(also in metrics.json).

Durability: BLF is written in small containers (``max_container_size``, public
python-can API) and the file object is flushed every ``FLUSH_EVERY_S``, so a SIGKILL of the
harness loses at most the frames of one open container (≈ 85 frames, ≈ 10 cycles). ASC is
text, flushed the same way. MF4 is recorded into the frame file ``bus.mf4.frames`` (flushed
the same way) and built when the recorder stops; after a SIGKILL ``rhonn-bus recover RUN_DIR``
builds it (layout, time base and recovery: can_db/logfiles.py). The MF4's channel times are
zero-based: simulated time in lockstep, receive time minus the start in realtime, the start
being the MDF header's ``start_time``.
"""

from __future__ import annotations

import copy
import heapq
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can

from can_db.codec import Codec, Decoded
from can_db.logfiles import FrameFile, finish_mf4, frames_path, set_asc_date
from can_db.process.rt import FIFO_PRIORITY, make_realtime
from can_db.secoc import SECURED
from can_db.transport.bus import BusDisconnected, open_bus
from can_db.transport.socketcan import rx_dropped as socket_rx_dropped

LOG_FORMATS = ("blf", "asc", "mf4")
RECORDER_NODE = "bus-recorder"  # the recorder's node name in the local hub's counts
POLL_S = 0.005  # the recorder looks for new frames this often when there were none, wall s
FLUSH_EVERY_S = 0.2  # file flush period, wall s: bounds what a SIGKILL of the harness loses
BLF_CONTAINER_BYTES = 4096  # ≈ 85 classic CAN frame objects per compressed BLF container
PERIOD_S = 0.01  # communication cycle, s (the DBC's GenMsgCycleTime)
FRAME_SLOT_S = 250e-6  # lockstep: stamp spacing of frames in one cycle, s
IN_CYCLE_CAP_S = 0.009  # a frame's offset inside its cycle is capped here, s
# the plant's frames before SYNC, with their SecOC authenticators when SecOC is on
PLANT_BURST = ("DRIVER_INPUTS", "DRIVER_INPUTS_AUTH", "MOTION_SENSORS", "MOTION_SENSORS_AUTH",
               "WHEEL_SPEEDS", "WHEEL_SPEEDS_AUTH", "VEHICLE_EST", "VEHICLE_EST_AUTH")
ECHOING = ("WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS")  # carry ECHO_CYCLE
ECHO_MODULO = 256
MAX_PENDING = 64  # frames held for a SYNC that never comes (dropped by a fault), then stamped
# Stamped frames held for time order until the next SYNC, at most: a flood with no SYNC (the
# plant gone) would otherwise grow the heap without end. 4096 frames are ≈ 270 cycles of the
# loop's 15 frames; past it the oldest are written at once (``released_early``).
MAX_HELD = 4096


class Mf4Writer:
    """MF4 writer for the recorder: frames go to the crash-safe frame file as they come,
    :meth:`stop` builds the MF4 from it (can_db/logfiles.py). ``start_s``: the log's start,
    wall clock Unix s (the MDF header's start time); ``zero_s``: subtracted from a frame's
    ``timestamp`` to give its channel time, s (``start_s`` for absolute stamps, 0 for
    stamps that already count from the start)."""

    def __init__(self, path: Path, start_s: float, note: str,
                 zero_s: float | None = None) -> None:
        self.path = path
        self._zero_s = start_s if zero_s is None else zero_s
        self.file = FrameFile(frames_path(path), start_s, note)  # flushed by the recorder

    def on_message_received(self, msg: can.Message) -> None:
        self.file.add(msg, msg.timestamp - self._zero_s)

    def stop(self) -> None:
        """Close the frame file and build the MF4 from it."""
        self.file.close()
        finish_mf4(self.path)


def open_writer(path: Path, start_s: float | None = None, note: str = "",
                zero_s: float | None = None) -> can.io.generic.MessageWriter | Mf4Writer:
    """Writer for ``path`` by suffix (.blf, .asc, .mf4): python-can's for BLF and ASC, the
    frame-file MF4 writer for MF4 (``start_s``, ``note``, ``zero_s``: see :class:`Mf4Writer`;
    ``start_s`` defaults to now)."""
    suffix = path.suffix.lower()
    if suffix == ".blf":
        return can.BLFWriter(path, max_container_size=BLF_CONTAINER_BYTES)
    if suffix == ".asc":
        return can.ASCWriter(path)
    if suffix == ".mf4":
        return Mf4Writer(path, time.time() if start_s is None else start_s, note, zero_s)
    raise ValueError(f"bus log {path}: use one of .{', .'.join(LOG_FORMATS)}")


class SimTimeStamper:
    """Lockstep time stamps: each frame's simulated time within its cycle (see module doc).

    ``feed(msg)`` returns the frames that are ready to be written, stamped (absolute,
    ``epoch_s`` + simulated s) and in time order. Plant frames are held until the SYNC that
    ends their burst tells the cycle's time; controller frames go to the cycle their
    ECHO_CYCLE names (an answer may arrive after the next burst has begun); a SecOC
    authenticator goes to the cycle of the frame it authenticates (the last frame of that ID:
    its sender sends it right after). So the stamps do not depend on how the answer reached
    the bus: in one atomic burst (local bus) or frame by frame (SocketCAN), where the plant's
    next burst can overtake the controller's last frames. Other frames go to the latest
    SYNC's cycle. Frames are released once the cycle after theirs has begun, so the file
    stays in time order.
    """

    def __init__(self, codec: Codec, epoch_s: float) -> None:
        self.codec, self.epoch_s = codec, epoch_s
        self._sync_id = codec.messages["SYNC"].frame_id
        self._burst_ids = {codec.messages[n].frame_id for n in PLANT_BURST}
        self._echo_ids = {codec.messages[n].frame_id for n in ECHOING}
        # authenticator id -> id of the frame it authenticates
        self._auth_of = {codec.messages[a].frame_id: codec.messages[d].frame_id
                         for d, a in SECURED.items()}
        self._placed_in: dict[int, list[float]] = {}  # frame id -> cycle of its latest frame
        self._burst: list[can.Message] = []  # plant frames waiting for their SYNC
        self._cycles: dict[int, list[float]] = {}  # echo (cycle % 256) -> [log time s, slot]
        self._current: list[float] = [0.0, 0]  # the latest SYNC's cycle
        self._shift_s = 0.0  # added after plant restarts so the time line never goes back
        self._last_sim_s = -math.inf  # last SIM_TIME seen (unshifted)
        self._out: list[tuple[float, int, can.Message]] = []  # heap: (stamp, seq, frame)
        self._seq = 0
        self.released_early = 0  # frames written before their cycle ended (MAX_HELD)

    def _place(self, msg: can.Message, cycle: list[float]) -> None:
        t = cycle[0] + min(cycle[1] * FRAME_SLOT_S, IN_CYCLE_CAP_S)
        cycle[1] += 1
        self._placed_in[msg.arbitration_id] = cycle
        msg.timestamp = self.epoch_s + t
        heapq.heappush(self._out, (t, self._seq, msg))
        self._seq += 1

    def _new_cycle(self, sim_s: float | None, echo: int | None) -> None:
        if sim_s is None:  # a corrupted SYNC: the cycle after the last one
            t = self._current[0] + PERIOD_S
        else:
            if sim_s < self._last_sim_s - 1e-9:  # plant restarted: continue the time line
                self._shift_s = self._current[0] + PERIOD_S - sim_s
            self._last_sim_s = sim_s
            t = sim_s + self._shift_s
        self._current = [t, 0]
        if echo is not None:
            self._cycles[echo] = self._current
            for old in [k for k in self._cycles if k not in
                        {(echo - i) % ECHO_MODULO for i in range(4)}]:
                del self._cycles[old]

    def _ready(self, before_s: float) -> list[can.Message]:
        out = []
        while self._out and self._out[0][0] < before_s:
            out.append(heapq.heappop(self._out)[2])
        return out

    def feed(self, msg: can.Message) -> list[can.Message]:
        """Frames ready to write (stamped, in time order)."""
        arb = msg.arbitration_id
        if arb in self._burst_ids:
            self._burst.append(msg)
            if len(self._burst) > MAX_PENDING:  # SYNC lost: stamp in the predicted cycle
                self._new_cycle(None, None)
                for m in self._burst:
                    self._place(m, self._current)
                self._burst.clear()
            return []
        if arb == self._sync_id:
            sync = self.codec.decode_message(msg)
            if isinstance(sync, Decoded):
                cycle = int(sync.values["CYCLE"])
                self._new_cycle(float(sync.values["SIM_TIME"]), cycle % ECHO_MODULO)
            else:
                self._new_cycle(None, None)
            for m in [*self._burst, msg]:
                self._place(m, self._current)
            self._burst.clear()
            return self._ready(self._current[0] - PERIOD_S / 2)  # up to the previous cycle
        target = self._current
        if arb in self._echo_ids:
            dec = self.codec.decode_message(msg)
            if isinstance(dec, Decoded):
                target = self._cycles.get(int(dec.values["ECHO_CYCLE"]), self._current)
        elif arb in self._auth_of:
            target = self._placed_in.get(self._auth_of[arb], self._current)
        self._place(msg, target)
        if len(self._out) <= MAX_HELD:
            return []
        self.released_early += 1  # oldest first: the file stays in order but for late answers
        return [heapq.heappop(self._out)[2]]

    def flush(self) -> list[can.Message]:
        """Everything still held (end of the run)."""
        for m in self._burst:
            self._place(m, self._current)
        self._burst.clear()
        return self._ready(math.inf)


def _iso_ms(unix_s: float) -> str:
    """``2026-01-31T12:00:00.123Z`` of a wall-clock time, Unix s."""
    return (time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(unix_s))
            + f".{int(unix_s % 1 * 1000):03d}Z")


def _cpus_beside_the_loop() -> set[int]:
    """The CPUs this process may use that ``$RHONN_RT_CPUS`` does not give to the loop's
    processes (empty when the loop is not pinned to a subset, or nothing is left)."""
    env = os.environ.get("RHONN_RT_CPUS")
    if not env or env == "all" or not hasattr(os, "sched_getaffinity"):
        return set()
    try:
        loop = {int(c) for c in env.split(",") if c.strip()}
    except ValueError:
        return set()
    return set(os.sched_getaffinity(0)) - loop


class BusRecorder:
    """A bus client in a background thread writing every received frame to a log file.

    It also follows the plant's SYNC frames (``sim_time_s``) so the harness can time its
    process-level faults in simulated seconds, and survives a bus-server restart.
    ``stamp``: "sim" (lockstep: simulated time) or "wall" (realtime: receive time).
    ``tap``: called in the recorder thread with a copy of every frame as received (wall
    time stamp), e.g. for the live rerun view.
    In lockstep on a local channel it joins as a lossless node: the hub waits for it rather
    than drop its frames (a slow recorder on a loaded machine slows the run, the log stays
    whole); in real time it must not hold the loop back, so a full queue drops and counts.
    """

    def __init__(self, spec: str, path: Path, reconnect_s: float = 10.0,
                 stamp: str = "wall", tap: Callable[[can.Message], None] | None = None,
                 rt: bool = False) -> None:
        if stamp not in ("sim", "wall"):
            raise ValueError(f"stamp must be 'sim' or 'wall', got {stamp!r}")
        self.path = path
        self.tap = tap
        self.rt = rt  # the recording thread asks for SCHED_FIFO below the loop's processes
        self.frames = 0
        self.sim_time_s = 0.0
        self.error: str | None = None
        self._rx_dropped_at_stop: int | None = None
        self._codec = Codec()
        self._sync_id = self._codec.messages["SYNC"].frame_id
        self._stop = threading.Event()
        # a barrier (arm_barrier): frames of these ids are not recorded; the last one's
        # arrival says every frame its sender sent before it is in the log
        self._barrier_ids: frozenset[int] = frozenset()
        self._barrier_end: int | None = None
        self._barrier_end_data = b""
        self._barrier_hit = threading.Event()
        mf4 = path.suffix.lower() == ".mf4"
        if stamp == "sim":
            self.epoch_s = float(math.floor(time.time()))  # whole second: exact in BLF's header
            self.time_base = (
                f"rhonn-tv bus log; time stamps: simulated time (lockstep), 0 s = the run's "
                f"start at wall clock "
                f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime(self.epoch_s))}")
        else:
            self.epoch_s = time.time()
            self.time_base = (
                f"rhonn-tv bus log; time stamps: wall clock at reception (realtime), 0 s = the "
                f"run's start at wall clock {_iso_ms(self.epoch_s)}")
        # MF4 in lockstep: the stamper counts from 0 so the channel times are the simulated
        # times exactly (an absolute stamp of ~1.8e9 s keeps only ~0.2 µs)
        self._writer = open_writer(path, self.epoch_s, self.time_base,
                                   zero_s=0.0 if mf4 and stamp == "sim" else None)
        self._stamper = (SimTimeStamper(self._codec, 0.0 if mf4 else self.epoch_s)
                         if stamp == "sim" else None)
        self._note_time_base()
        try:
            # on a local channel the hub counts this node's drops under RECORDER_NODE
            local = {"node_name": RECORDER_NODE} if spec.startswith("local:") else {}
            if local and stamp == "sim":
                local["lossless"] = True
            self.bus = open_bus(spec, reconnect_s=reconnect_s, **local)
        except Exception:
            self._writer.stop()
            raise
        self._thread = threading.Thread(target=self._run, name="bus-recorder", daemon=True)

    @property
    def rx_dropped(self) -> int | None:
        """Frames the kernel dropped for the recorder's socket (SocketCAN; after ``stop``:
        the count at its end); None on a bus that keeps no such count here (the local hub
        counts them under RECORDER_NODE)."""
        return self._rx_dropped_at_stop if self._stop.is_set() else socket_rx_dropped(self.bus)

    @property
    def released_early(self) -> int:
        """Lockstep: frames written before their cycle ended because the time-order heap
        held MAX_HELD frames (a flood without SYNC); 0 in real time."""
        return self._stamper.released_early if self._stamper is not None else 0

    def _note_time_base(self) -> None:
        """The time base as the log's first event (BLF marker, ASC comment)."""
        log_event = getattr(self._writer, "log_event", None)  # public on BLF and ASC writers
        if callable(log_event):
            log_event(self.time_base, self.epoch_s)

    def start(self) -> BusRecorder:
        self._thread.start()
        return self

    def _write(self, msgs: list[can.Message]) -> None:
        for m in msgs:
            self._writer.on_message_received(m)

    def _run(self) -> None:
        if self.rt:
            others = _cpus_beside_the_loop()  # (before make_realtime pins this thread)
            make_realtime("bus-recorder", priority=FIFO_PRIORITY - 10)
            if others:
                # off the loop's CPU: its work runs beside the loop, not in it
                os.sched_setaffinity(0, others)
                print(f"bus-recorder: CPUs {sorted(others)} (the loop has "
                      f"{os.environ.get('RHONN_RT_CPUS')})", file=sys.stderr, flush=True)
        file = getattr(self._writer, "file", None)
        last_flush = time.monotonic()
        recv = self.bus.recv
        try:
            while not self._stop.is_set():
                msg = recv(timeout=0.0)
                if msg is None:
                    # Poll, don't block: while this thread sleeps here instead of waiting on
                    # the socket, a frame sent to it wakes nobody (on another CPU every
                    # wake-up is an inter-processor interrupt: 19.7-20.7x instead of
                    # 25.1-25.7x real time, measured with a blocking recorder there); below
                    # the loop's priority on its CPU it starved instead and the hub dropped
                    # 82 % of its frames in a 300 s lockstep run (its queue is finite).
                    self._stop.wait(POLL_S)
                    if file is not None and time.monotonic() - last_flush > FLUSH_EVERY_S:
                        file.flush()
                        last_flush = time.monotonic()
                    continue
                if msg.arbitration_id in self._barrier_ids:
                    if msg.arbitration_id == self._barrier_end and \
                            bytes(msg.data).startswith(self._barrier_end_data):
                        self._barrier_hit.set()
                    continue
                self.frames += 1
                if self.tap is not None:
                    self.tap(copy.copy(msg))
                if msg.arbitration_id == self._sync_id:
                    sync = self._codec.decode_message(msg)
                    if isinstance(sync, Decoded):
                        self.sim_time_s = sync.values["SIM_TIME"]
                if self._stamper is not None:
                    self._write(self._stamper.feed(msg))
                else:
                    self._write([msg])
                if file is not None and time.monotonic() - last_flush > FLUSH_EVERY_S:
                    file.flush()
                    last_flush = time.monotonic()
        except BusDisconnected as exc:
            self.error = str(exc)

    def arm_barrier(self, ids: frozenset[int], end_id: int, end_data: bytes = b"") -> None:
        """From now on frames with ``ids`` are not recorded, and one with ``end_id`` whose
        data start with ``end_data`` (a response that its sender sends after all its frames
        of the run; the other diagnostic responses before it do not end it) ends
        :meth:`wait_barrier`."""
        self._barrier_hit.clear()
        self._barrier_end_data = bytes(end_data)
        self._barrier_ids, self._barrier_end = frozenset(ids), end_id

    def wait_barrier(self, timeout_s: float) -> bool:
        """True once the armed barrier's end frame arrived (within ``timeout_s``, wall s)."""
        return self._barrier_hit.wait(timeout_s)

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
        if self._stamper is not None:
            self._write(self._stamper.flush())
        self._writer.stop()
        self._rx_dropped_at_stop = socket_rx_dropped(self.bus)
        self.bus.shutdown()
        if self.path.suffix.lower() == ".asc":
            set_asc_date(self.path, self.epoch_s)  # the header's date: the log's start
