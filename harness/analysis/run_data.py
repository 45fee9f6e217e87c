"""Load one run directory (truth trace, bus log, controller timing) into numpy arrays.

Every loader is robust to missing, partial and truncated files: the plant flushes its truth
trace per row and a killed process leaves half a line, a killed logger leaves a truncated
BLF. Loaders then return what was readable (possibly empty arrays) and never raise.

Bus alignment (see docs/can-matrix.md): the plant sends its frames of cycle k and ends
the burst with ``SYNC(CYCLE=k, SIM_TIME)``, so a plant frame belongs to the *next* SYNC. The
controller answers with frames carrying ``ECHO_CYCLE = k mod 256``; the echo is unwrapped
against the most recent SYNC seen before the frame (the largest cycle <= that SYNC's cycle
congruent to the echo), so late answers are attributed to the cycle they answer.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from can_db.codec import Codec, Decoded
from harness.run.marker import report_stale

TRUTH_FILE = "truth.csv"
BUS_FILE = "bus.blf"
#: Bus log names a run may hold (``--log-format``); the first that exists is read.
BUS_FILES = ("bus.blf", "bus.asc", "bus.mf4")
TIMING_FILE = "controller_timing.csv"
META_FILE = "meta.json"

#: Name of the pseudo-message in ``RunData.bus`` that lists rejected frames (not a DBC name).
REJECTED_KEY = "_REJECTED"
#: Messages sent by the plant (they precede the SYNC that ends their burst).
PLANT_MESSAGES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")
#: Messages sent by the controller, aligned by their ECHO_CYCLE (CTRL_REFS has none: it takes
#: the echo of a WHEEL_TORQUE_CMD/CTRL_STATUS logged after the same SYNC, else that SYNC).
CONTROLLER_MESSAGES = ("WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS")
ECHO_MODULO = 256
NOMINAL_PERIOD_S = 0.01


@dataclass
class RunData:
    """Everything recorded for one run.

    * ``truth``: truth-trace column name -> array (one value per 10 ms cycle, SI units).
    * ``bus``: message name -> {signal -> array (physical DBC units), ``t_log`` (logger
      timestamp, s), ``sim_time_s`` (aligned via SYNC, s; NaN if unknown), ``cycle`` (unwrapped
      SYNC cycle, -1 if unknown), ``counter`` (alive counter)}. ``bus[REJECTED_KEY]`` lists
      rejected frames: ``t_log``, ``sim_time_s``, ``cycle``, ``frame_id``, ``reason`` (str).
    * ``timing``: controller_timing.csv column -> array.
    * ``rejections``: rejected frame count by reason (bus log decode only).
    * ``meta``: free-form run metadata (scenario, controller, ``scenario_end_s`` …).
    """

    truth: dict[str, np.ndarray] = field(default_factory=dict)
    bus: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    timing: dict[str, np.ndarray] = field(default_factory=dict)
    rejections: dict[str, int] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def truth_col(self, name: str) -> np.ndarray:
        """A truth column as float array (empty if absent)."""
        return np.asarray(self.truth.get(name, _EMPTY), dtype=float)

    def bus_sig(self, message: str, signal: str) -> np.ndarray:
        """One signal (or ``t_log``/``sim_time_s``/``cycle``) of a message (empty if absent)."""
        return np.asarray(self.bus.get(message, {}).get(signal, _EMPTY))

    def timing_col(self, name: str) -> np.ndarray:
        """A controller-timing column as float array (empty if absent)."""
        return np.asarray(self.timing.get(name, _EMPTY), dtype=float)

    @property
    def n_cycles(self) -> int:
        """Number of rows of the truth trace."""
        return len(next(iter(self.truth.values()), _EMPTY))


_EMPTY = np.zeros(0)


def read_numeric_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a header + numeric-rows CSV into column arrays; tolerant of partial files.

    A last line without a terminating newline is dropped (the writer flushes whole rows, so it
    was cut mid-write), as is any row whose field count differs from the header. Empty or
    non-numeric fields read as NaN. Missing or unreadable file -> ``{}``; a header-only
    file -> empty arrays.
    """
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return {}
    lines = text.splitlines()
    if not lines:
        return {}
    if not text.endswith(("\n", "\r")):
        lines = lines[:-1]
        if not lines:
            return {}
    header = [h.strip() for h in lines[0].split(",")]
    rows: list[list[float]] = []
    for line in lines[1:]:
        parts = line.split(",")
        if len(parts) != len(header):
            continue
        try:
            rows.append([float(p) for p in parts])
        except ValueError:  # empty or non-numeric fields (e.g. a text column) read as NaN
            rows.append([_to_float(p) for p in parts])
    data = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    return {name: data[:, i].copy() for i, name in enumerate(header) if name}


def _to_float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def load_truth_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Load the plant's truth trace (``t_s``, ``cycle``, states in SI units…)."""
    return read_numeric_csv(path)


def load_timing_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Load the controller's per-cycle timing (``step_us``, ``turnaround_us``, ``period_us``…)."""
    return read_numeric_csv(path)


def _read_frames(path: Path) -> list[Any]:
    """All frames readable from a log; stops quietly at a truncated/corrupt tail."""
    frames: list[Any] = []
    if not path.is_file() or path.stat().st_size == 0:
        return frames
    try:
        reader = can.LogReader(str(path))
    except Exception:  # a corrupt header means "no frames", never a crash
        return frames
    try:
        for msg in reader:
            frames.append(msg)
    except Exception:  # truncated container: keep what was read
        pass
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            with contextlib.suppress(Exception):
                stop()
    return frames


def load_bus_log(path: str | Path, codec: Any | None = None
                 ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, int]]:
    """Decode every frame of a bus log (.blf/.asc/… via ``can.LogReader``).

    Returns ``(bus, rejections)``: ``bus`` maps message name -> signal arrays plus ``t_log``,
    ``sim_time_s``, ``cycle``, ``counter`` (see :class:`RunData`) and ``bus[REJECTED_KEY]``;
    ``rejections`` counts rejected frames by reason. Missing/corrupt file -> empty.
    """
    codec = codec or Codec()
    frames = _read_frames(Path(path))

    # Pass 1: decode, keep order. Each record: (name, values, counter, t_log).
    records: list[tuple[str, dict[str, float], int, float]] = []
    rejected: list[tuple[float, int, str, int]] = []  # t_log, frame_id, reason, record index
    rejections: dict[str, int] = {}
    for msg in frames:
        res = codec.decode_message(msg)
        if isinstance(res, Decoded):
            records.append((res.name, res.values, res.counter, float(msg.timestamp)))
        else:
            reason = str(res.reason.value)
            rejections[reason] = rejections.get(reason, 0) + 1
            rejected.append((float(msg.timestamp), int(msg.arbitration_id), reason, len(records)))

    # Pass 2: cycle of every record. Plant frames take the next SYNC's cycle; controller
    # frames unwrap their echo against the previous SYNC; SYNC carries its own.
    n = len(records)
    cycles = np.full(n, -1, dtype=np.int64)
    last_sync = -1
    last_echo = -1
    echo_since_sync = False  # an echoed frame of the current answer was already seen
    pending_plant: list[int] = []
    sync_cycle_after: list[int] = [-1] * (n + 1)  # previous-SYNC cycle before record i
    for i, (name, values, _, _) in enumerate(records):
        sync_cycle_after[i] = last_sync
        if name == "SYNC":
            last_sync = int(values["CYCLE"])
            cycles[i] = last_sync
            echo_since_sync = False
            for j in pending_plant:
                cycles[j] = last_sync
            pending_plant.clear()
        elif name in PLANT_MESSAGES:
            pending_plant.append(i)
        elif "ECHO_CYCLE" in values:
            if last_sync >= 0:
                echo = int(values["ECHO_CYCLE"])
                last_echo = last_sync - ((last_sync - echo) % ECHO_MODULO)
                echo_since_sync = True
                cycles[i] = last_echo
        elif name in CONTROLLER_MESSAGES:
            # CTRL_REFS has no echo: same answer as the echoed frame just before it, else the
            # answer to the latest SYNC.
            cycles[i] = last_echo if echo_since_sync else last_sync
    sync_cycle_after[n] = last_sync
    for j in pending_plant:  # burst cut off before its SYNC
        cycles[j] = last_sync + 1 if last_sync >= 0 else -1

    sim_time = _cycle_to_sim_time(records, cycles)

    bus: dict[str, dict[str, list[float]]] = {}
    for i, (name, values, counter, t_log) in enumerate(records):
        cols = bus.setdefault(name, {"t_log": [], "sim_time_s": [], "cycle": [], "counter": []})
        for sig, val in values.items():
            cols.setdefault(sig, []).append(val)
        cols["t_log"].append(t_log)
        cols["sim_time_s"].append(sim_time[i])
        cols["cycle"].append(int(cycles[i]))
        cols["counter"].append(counter)
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, cols in bus.items():
        out[name] = {k: np.asarray(v, dtype=np.int64 if k in ("cycle", "counter") else float)
                     for k, v in cols.items()}

    rej_cycle = np.asarray([sync_cycle_after[idx] for *_, idx in rejected], dtype=np.int64)
    out[REJECTED_KEY] = {
        "t_log": np.asarray([r[0] for r in rejected], dtype=float),
        "frame_id": np.asarray([r[1] for r in rejected], dtype=np.int64),
        "reason": np.asarray([r[2] for r in rejected], dtype=object),
        "cycle": rej_cycle,
        "sim_time_s": _lookup_sim_time(records, cycles, rej_cycle),
    }
    return out, rejections


def _sync_table(records: list[tuple[str, dict[str, float], int, float]]
                ) -> tuple[np.ndarray, np.ndarray]:
    cyc = [int(v["CYCLE"]) for name, v, _, _ in records if name == "SYNC"]
    sim = [float(v["SIM_TIME"]) for name, v, _, _ in records if name == "SYNC"]
    return np.asarray(cyc, dtype=np.int64), np.asarray(sim, dtype=float)


def _lookup_sim_time(records: list[tuple[str, dict[str, float], int, float]],
                     cycles: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Sim time of each queried cycle: the SYNC's SIM_TIME, else extrapolated at the SYNC rate."""
    sync_cyc, sync_sim = _sync_table(records)
    out = np.full(len(query), math.nan)
    if sync_cyc.size == 0 or len(query) == 0:
        return out
    table = dict(zip(sync_cyc.tolist(), sync_sim.tolist(), strict=True))
    if sync_cyc.size >= 2:
        dcyc, dsim = np.diff(sync_cyc), np.diff(sync_sim)
        ok = dcyc > 0
        dt = float(np.median(dsim[ok] / dcyc[ok])) if ok.any() else NOMINAL_PERIOD_S
    else:
        dt = NOMINAL_PERIOD_S
    ref_c, ref_t = int(sync_cyc[-1]), float(sync_sim[-1])
    for i, c in enumerate(query.tolist()):
        if c < 0:
            continue
        t = table.get(c)
        out[i] = t if t is not None else ref_t + (c - ref_c) * dt
    return out


def _cycle_to_sim_time(records: list[tuple[str, dict[str, float], int, float]],
                       cycles: np.ndarray) -> np.ndarray:
    return _lookup_sim_time(records, cycles, cycles)


def load_run(dir: str | Path, meta: dict[str, Any] | None = None) -> RunData:
    """Load ``DIR/truth.csv``, ``DIR/bus.blf``, ``DIR/controller_timing.csv`` (+ ``meta.json``).

    ``meta`` entries override those of ``DIR/meta.json``. ``meta["missing_files"]`` lists the
    expected files that were absent. Never raises for missing or partial files.
    """
    run_dir = Path(dir)

    report_stale(run_dir)  # a harness killed while writing here: one line on stderr
    merged: dict[str, Any] = {}
    meta_path = run_dir / META_FILE
    if meta_path.is_file():
        try:
            loaded = json.loads(meta_path.read_text())
            if isinstance(loaded, dict):
                merged.update(loaded)
        except (OSError, ValueError):
            pass
    merged.update(meta or {})
    merged.setdefault("run_dir", str(run_dir))
    bus_file = next((f for f in BUS_FILES if (run_dir / f).is_file()), BUS_FILE)
    merged["missing_files"] = [f for f in (TRUTH_FILE, bus_file, TIMING_FILE)
                               if not (run_dir / f).is_file()]
    bus, rejections = load_bus_log(run_dir / bus_file)
    return RunData(truth=load_truth_csv(run_dir / TRUTH_FILE), bus=bus,
                   timing=load_timing_csv(run_dir / TIMING_FILE), rejections=rejections,
                   meta=merged)
