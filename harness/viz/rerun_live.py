"""Live rerun view of a running closed loop (``rhonn-harness run --rerun-live``).

A rerun web viewer is started as a child process bound to 127.0.0.1 only (``rerun
--serve-web --bind 127.0.0.1``; the CLI's default bind is all interfaces), after
``rerun analytics disable``. The harness connects to it as a logging client and, about
five times a second, streams what is new:

* plant states from the truth trace the plant writes row by row (``truth.csv.rows`` while
  it runs, ``truth.csv`` after; can_db/process/rowlog.py);
* controller outputs and status from the frames the bus recorder sees (CTRL_REFS,
  CTRL_STATUS, WHEEL_TORQUE_CMD), each placed at the cycle its ECHO_CYCLE names;
* timing from the controller's row-by-row ``controller_timing.csv(.rows)``.

Entity paths, timelines (``sim_time``, ``cycle``), colours and the blueprint are the ones of
the post-run file (:mod:`harness.viz.rerun_log`); the recording id is the same run name.
The event log and the KPI summary need the whole run and are sent when the run has ended.
"""

from __future__ import annotations

import importlib.util
import os
import queue
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import can
import numpy as np
import rerun as rr

from can_db.codec import Codec, Decoded
from can_db.process.parent import die_with_parent
from can_db.process.rowlog import RowTail, rows_path
from harness.analysis.run_data import RunData
from harness.run.spec import GRPC_PORT_OFFSET
from harness.viz import rerun_log as rl

CTRL_MESSAGES = ("CTRL_REFS", "CTRL_STATUS", "WHEEL_TORQUE_CMD")
ECHO_MODULO = 256


class CsvTail:
    """The rows appended to a growing CSV since the last call (whole lines only). Follows
    the file when it is replaced (a restarted plant starts a new truth.csv)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: TextIO | None = None
        self._inode: int | None = None
        self._partial = ""
        self.columns: list[str] | None = None

    def _open_if_new(self) -> None:
        try:
            inode = os.stat(self.path).st_ino
        except OSError:
            return
        if inode != self._inode:
            if self._fh is not None:
                self._fh.close()
            self._fh = open(self.path, encoding="utf-8", errors="replace")  # noqa: SIM115
            self._inode, self._partial, self.columns = inode, "", None

    def rows(self) -> dict[str, np.ndarray]:
        """New rows as column arrays (empty dict when nothing new)."""
        self._open_if_new()
        if self._fh is None:
            return {}
        lines = (self._partial + self._fh.read()).split("\n")
        self._partial = lines.pop()  # an unfinished line waits for its end
        if self.columns is None and lines:
            self.columns = [c.strip() for c in lines.pop(0).split(",")]
        if not lines or self.columns is None:
            return {}
        rows = [r.split(",") for r in lines if r]
        rows = [r for r in rows if len(r) == len(self.columns)]
        if not rows:
            return {}
        try:
            data = np.array(rows, dtype=float)
        except ValueError:
            return {}
        return {c: data[:, i] for i, c in enumerate(self.columns)}

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


class LogTail:
    """New rows of a per-cycle log that is a row file while its writer runs and a CSV
    after (can_db/process/rowlog.py): the row file when one was seen, else the CSV."""

    def __init__(self, csv_path: Path) -> None:
        self._rows = RowTail(rows_path(csv_path))
        self._csv = CsvTail(csv_path)

    def rows(self) -> dict[str, np.ndarray]:
        new = self._rows.rows()
        if self._rows.opened:
            return new
        return self._csv.rows()

    def close(self) -> None:
        self._rows.close()
        self._csv.close()


class FrameBatcher:
    """Bus frames → ``RunData.bus`` columns, with cycle and simulated time from the latest
    SYNC (controller frames: the cycle their ECHO_CYCLE names)."""

    def __init__(self, codec: Codec, period_s: float = rl.DEFAULT_PERIOD_S) -> None:
        self.codec, self.period_s = codec, period_s
        self._cycle, self._sim = -1, 0.0

    def columns(self, frames: Sequence[can.Message]) -> dict[str, dict[str, np.ndarray]]:
        acc: dict[str, dict[str, list[float]]] = {}
        for msg in frames:
            dec = self.codec.decode_message(msg)
            if not isinstance(dec, Decoded):
                continue
            if dec.name == "SYNC":
                self._cycle, self._sim = int(dec.values["CYCLE"]), float(dec.values["SIM_TIME"])
            if dec.name not in CTRL_MESSAGES or self._cycle < 0:
                cycle, sim = self._cycle, self._sim
            else:
                back = (self._cycle - int(dec.values.get("ECHO_CYCLE", self._cycle))) \
                    % ECHO_MODULO
                cycle, sim = self._cycle - back, self._sim - back * self.period_s
            cols = acc.setdefault(dec.name, {"t_log": [], "sim_time_s": [], "cycle": []})
            cols["t_log"].append(float(msg.timestamp))
            cols["sim_time_s"].append(sim)
            cols["cycle"].append(float(cycle))
            for k, v in dec.values.items():
                cols.setdefault(k, []).append(float(v))
        return {m: {k: np.asarray(v, dtype=float) for k, v in c.items()} for m, c in acc.items()}


def web_viewer_url(web_port: int, grpc_port: int) -> str:
    """The address to open in a browser (loopback)."""
    return (f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp://127.0.0.1:{grpc_port}/proxy")


def _wait_for_port(port: int, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return True
        except OSError:
            time.sleep(0.2)
    return False


def rerun_binary() -> str:
    """The rerun viewer binary shipped with the SDK (same version). Started directly, not
    through the ``rerun`` wrapper script, which would leave the binary running when it is
    stopped (the wrapper's child is not signalled)."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        exe = Path(spec.origin).with_name("rerun")
        if exe.is_file():
            return str(exe)
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.exists() else "rerun"


def start_viewer(web_port: int, log_path: Path | None = None) -> subprocess.Popen[bytes]:
    """``rerun analytics disable``, then a web viewer + gRPC proxy on 127.0.0.1 only."""
    rerun_exe = rerun_binary()
    subprocess.run([rerun_exe, "analytics", "disable"], check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=30)
    grpc_port = web_port + GRPC_PORT_OFFSET
    out = open(log_path, "wb") if log_path else subprocess.DEVNULL  # noqa: SIM115
    proc = subprocess.Popen(
        [rerun_exe, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc_port),
         "--web-viewer-port", str(web_port), "--server-memory-limit", "25%",
         "--expect-data-soon"],
        stdout=out, stderr=subprocess.STDOUT, preexec_fn=die_with_parent)
    if not _wait_for_port(grpc_port, 30.0) or not _wait_for_port(web_port, 10.0):
        proc.kill()
        raise RuntimeError(f"rerun web viewer did not come up on 127.0.0.1:{web_port}/"
                           f"{grpc_port}")
    return proc


class LiveRerun:
    """One live recording in a loopback web viewer; feed it with :meth:`poll`."""

    def __init__(self, out_dir: Path, recording_name: str, course: Sequence[np.ndarray],
                 ref_path: np.ndarray | None, cones: np.ndarray | None, web_port: int = 9090
                 ) -> None:
        self.out_dir, self.name = out_dir, recording_name
        self.web_port, self.grpc_port = web_port, web_port + GRPC_PORT_OFFSET
        self.url = web_viewer_url(self.web_port, self.grpc_port)
        self.frames: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self.viewer = start_viewer(web_port, out_dir / "rerun_viewer.log")
        self.rec = rr.RecordingStream(application_id=rl.APPLICATION_ID,
                                      recording_id=recording_name)
        blueprint = rl.build_blueprint(rl.course_bounds(course, ref_path, cones))
        self.rec.connect_grpc(f"rerun+http://127.0.0.1:{self.grpc_port}/proxy",
                              default_blueprint=blueprint)
        self.rec.send_recording_name(recording_name)
        rl.log_course(self.rec, course, ref_path, cones)
        self._writer = rl._Writer(self.rec)
        self._truth = LogTail(out_dir / "truth.csv")
        self._timing = LogTail(out_dir / "controller_timing.csv")
        self._frames = FrameBatcher(Codec())
        self._path: list[np.ndarray] = []
        self.polls = 0

    def tap(self, msg: can.Message) -> None:
        """Called by the bus recorder's thread for every frame (thread-safe queue)."""
        self.frames.put(msg)

    def poll(self) -> None:
        """Stream everything new since the last call."""
        frames: list[can.Message] = []
        while True:
            try:
                frames.append(self.frames.get_nowait())
            except queue.Empty:
                break
        run = RunData(truth=self._truth.rows(), bus=self._frames.columns(frames),
                      timing=self._timing.rows(), meta={"comm_period_s": rl.DEFAULT_PERIOD_S})
        rl.log_time_series(self._writer, run)
        xy = rl.log_vehicle(self.rec, run)
        if xy is not None and xy.size:
            self._path.append(xy)
            rl.log_driven_path(self.rec, np.concatenate(self._path))
        self.polls += 1

    def finish(self, run: RunData, metrics: dict[str, Any] | None = None) -> None:
        """After the run: the last rows, the event log and the summary of the whole run
        (``metrics``: its verdicts and partial-run label, when known)."""
        self.poll()
        rl.log_events(self.rec, run, metrics)
        rl.log_summary(self.rec, run, self.name, metrics)
        self.rec.flush()

    def close(self) -> None:
        """Disconnect and stop the viewer."""
        self._truth.close()
        self._timing.close()
        try:
            self.rec.flush()
            self.rec.disconnect()
        finally:
            if self.viewer.poll() is None:
                self.viewer.terminate()
                try:
                    self.viewer.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    self.viewer.kill()


def keep_viewer_open(live: Any, hold_s: float | None = None) -> None:
    """Block until Ctrl-C or for ``hold_s`` wall seconds (the run is over; the viewer keeps
    the recording)."""
    end = None if hold_s is None else time.monotonic() + hold_s
    try:
        while live.viewer.poll() is None and (end is None or time.monotonic() < end):
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
