"""Checkpointed learning: the controller's learned state survives a process restart.

File format (``.npz``, numpy's zip of ``.npy`` arrays, loaded with ``allow_pickle=False``):
one float64 array per ``Controller.get_state()`` key (floats as 0-d arrays) plus
``__header__``: UTF-8 JSON as a uint8 array with

  format (= "rhonn-tv-checkpoint"), version (= FORMAT_VERSION), controller (name),
  config_hash (sha256 of the controller TOML and vehicle parameters, 16 hex digits),
  steps (MPC steps learned since the cold start), scalars (keys that were floats).

Writes are atomic: a temp file in the same directory, fsync, ``os.replace``, fsync of the
directory. A crash at any moment leaves either the previous checkpoint or the new one, never
a torn file (at worst a stale ``.NAME.*.tmp`` that the next start removes).

Restore is all-or-nothing: the file must match the format version, the controller name,
the config hash, the exact key set and every array shape of a fresh controller's state, and
hold no ±inf (NaN only where a cold controller holds NaN, e.g. "no pending prediction").
Anything else — missing, unreadable, truncated, mismatched — is reported with a reason and
ignored: the controller cold-starts; nothing here raises into the caller. After a restore the
adaptive model's pending one-step prediction is dropped: it belongs to the stopped run's
time line, and learning from it would inject one large bogus error into the weights.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from controller.core.registry import load_controller_config

FORMAT = "rhonn-tv-checkpoint"
FORMAT_VERSION = 1
HEADER_KEY = "__header__"


class Checkpointable(Protocol):
    """What a controller offers for checkpoints (MpcController, PassiveController)."""

    name: str
    ts: float

    def reset(self) -> None: ...
    def get_state(self) -> dict[str, np.ndarray | float]: ...
    def set_state(self, d: dict[str, np.ndarray | float]) -> None: ...


@dataclass(slots=True)
class RestoreResult:
    """Outcome of a restore: restored or not, why, and the MPC steps learned so far."""

    restored: bool
    reason: str
    steps: int = 0


def config_hash(controller_name: str, config: str | Path | None = None) -> str:
    """16 hex digits identifying the controller's configuration (TOML + vehicle data)."""
    cfg = load_controller_config(config)
    blob = json.dumps({"controller": controller_name, "raw": cfg.raw,
                       "vehicle": asdict(cfg.params)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _fsync_dir(directory: Path) -> None:
    """Make the rename durable (POSIX); silently skipped where directories cannot be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_checkpoint(path: str | Path, controller: Checkpointable, *, cfg_hash: str,
                    steps: int, _before_replace: Callable[[Path], None] | None = None
                    ) -> None:
    """Atomically write the controller's state to ``path`` (raises OSError on failure,
    leaving any previous checkpoint untouched). ``_before_replace`` is a test hook called
    with the fsynced temp file just before the rename."""
    path = Path(path)
    state = controller.get_state()
    arrays: dict[str, np.ndarray] = {}
    scalars: list[str] = []
    for key, value in state.items():
        if key == HEADER_KEY:
            raise ValueError(f"state key {HEADER_KEY!r} is reserved")
        if isinstance(value, np.ndarray):
            arrays[key] = np.array(value, dtype=np.float64)
        else:
            arrays[key] = np.array(float(value), dtype=np.float64)
            scalars.append(key)
    header = {"format": FORMAT, "version": FORMAT_VERSION, "controller": controller.name,
              "config_hash": cfg_hash, "steps": int(steps), "scalars": sorted(scalars)}
    arrays[HEADER_KEY] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        if _before_replace is not None:
            _before_replace(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(directory)


def read_checkpoint(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Header and arrays of a checkpoint file (raises on anything unreadable)."""
    with np.load(Path(path), allow_pickle=False) as npz:
        data = {k: np.array(npz[k]) for k in npz.files}
    raw = data.pop(HEADER_KEY, None)
    if raw is None or raw.dtype != np.uint8 or raw.ndim != 1:
        raise ValueError("no header")
    header = json.loads(raw.tobytes().decode())
    if not isinstance(header, dict):
        raise ValueError("header is not an object")
    return header, data


def _check(header: dict[str, Any], data: dict[str, np.ndarray],
           template: dict[str, np.ndarray | float], name: str, cfg_hash: str | None,
           limits: StateLimits) -> str | None:
    """Why the checkpoint does not fit the controller, or None if it does."""
    if header.get("format") != FORMAT or header.get("version") != FORMAT_VERSION:
        return (f"format {header.get('format')!r} version {header.get('version')!r}, "
                f"expected {FORMAT!r} version {FORMAT_VERSION}")
    if header.get("controller") != name:
        return f"controller {header.get('controller')!r}, expected {name!r}"
    if cfg_hash is not None and header.get("config_hash") != cfg_hash:
        return f"config hash {header.get('config_hash')!r}, expected {cfg_hash!r}"
    if set(data) != set(template):
        missing = sorted(set(template) - set(data))
        extra = sorted(set(data) - set(template))
        return f"state keys differ: missing {missing}, unexpected {extra}"
    for key, cold in template.items():
        cold_arr = np.asarray(cold, dtype=np.float64)
        arr = data[key]
        if arr.shape != cold_arr.shape:
            return f"{key}: shape {arr.shape}, expected {cold_arr.shape}"
        if arr.dtype != np.float64:
            return f"{key}: dtype {arr.dtype}, expected float64"
        if np.isinf(arr).any():
            return f"{key}: infinite values"
        if np.isnan(arr).any() and not np.isnan(cold_arr).any():
            return f"{key}: NaN values"
    steps = header.get("steps")
    if not isinstance(steps, int) or steps < 0:
        return f"bad step count {steps!r}"
    return value_problem(data, limits)


@dataclass(frozen=True, slots=True)
class StateLimits:
    """What a learned state may hold: |weights| ≤ w_max (u), covariances symmetric with a
    positive diagonal and a trace ≤ trace_max (u²): the EKF's own bounds ([rhonn.ekf]); any
    other value ≤ other_max in magnitude (the QP's numeric limit)."""

    w_max: float = 1e3
    trace_max: float = 1e3
    other_max: float = 1e12

    @classmethod
    def of(cls, config: Any) -> StateLimits:
        """The limits of a loaded ControllerConfig (its [rhonn.ekf] bounds)."""
        ekf = config.rhonn.ekf
        return cls(w_max=float(ekf.w_max), trace_max=float(ekf.trace_max))


def value_problem(data: dict[str, np.ndarray], limits: StateLimits) -> str | None:
    """Why the state's values cannot be a state the controller reaches (weights beyond the
    EKF's bound, a covariance that is not one), or None. Tolerances: the EKF keeps W within
    w_max exactly, P symmetric to rounding (1e-9 relative) and its trace within trace_max
    (reset above it; 1 % margin for the last update before the check)."""
    for key, arr in data.items():
        a = np.nan_to_num(np.asarray(arr, dtype=np.float64), nan=0.0)
        if key.endswith(".W") or key.endswith(".w_slow"):
            if np.abs(a).max(initial=0.0) > limits.w_max:
                return f"{key}: |weights| above w_max = {limits.w_max:g}"
        elif key.endswith(".P") and a.ndim == 3:
            diag = np.diagonal(a, axis1=1, axis2=2)
            if (diag <= 0.0).any():
                return f"{key}: a covariance with a diagonal entry <= 0"
            if np.abs(a - a.transpose(0, 2, 1)).max() > 1e-9 * np.abs(a).max():
                return f"{key}: a covariance that is not symmetric"
            if diag.sum(axis=1).max() > 1.01 * limits.trace_max:
                return f"{key}: a covariance trace above trace_max = {limits.trace_max:g}"
        elif np.abs(a).max(initial=0.0) > limits.other_max:
            return f"{key}: |values| above {limits.other_max:g}"
    return None


def _drop_pending_prediction(controller: Checkpointable) -> None:
    """A restart is a break in time: the one-step prediction recorded before the stop is
    for a state the new run never measures, and learning from it would corrupt the weights
    with one large bogus error. Drop it (the learned weights and covariances stay)."""
    model = getattr(controller, "model", None)
    forget = getattr(model, "forget_record", None)
    if callable(forget):
        forget()


def load_checkpoint(path: str | Path, controller: Checkpointable, *,
                    cfg_hash: str | None = None,
                    limits: StateLimits | None = None) -> RestoreResult:
    """Restore ``controller`` from ``path`` if it matches; otherwise leave it cold.

    cfg_hash: expected config hash (None: not checked); limits: the values a state may hold
    (None: the EKF defaults). Never raises."""
    path = Path(path)
    if not path.exists():
        return RestoreResult(False, f"no checkpoint at {path}: cold start")
    try:
        header, data = read_checkpoint(path)
    except Exception as exc:  # any corruption (zip, npy, JSON, I/O): cold start
        return RestoreResult(False, f"unreadable checkpoint {path}: "
                                    f"{type(exc).__name__}: {exc}; cold start")
    try:
        template = controller.get_state()
        problem = _check(header, data, template, controller.name, cfg_hash,
                         limits or StateLimits())
    except Exception as exc:
        problem = f"cannot check: {type(exc).__name__}: {exc}"
    if problem is not None:
        return RestoreResult(False, f"checkpoint {path} ignored ({problem}); cold start")
    scalars = set(header.get("scalars", []))
    state: dict[str, np.ndarray | float] = {
        k: (float(v) if k in scalars else v) for k, v in data.items()}
    try:
        controller.set_state(state)
    except Exception as exc:  # a partial restore must not survive: back to cold
        controller.reset()
        return RestoreResult(False, f"checkpoint {path} rejected by the controller "
                                    f"({type(exc).__name__}: {exc}); cold start")
    _drop_pending_prediction(controller)
    steps = int(header["steps"])
    return RestoreResult(True, f"restored {path} ({steps} MPC steps learned)", steps)


class CheckpointManager:
    """Restore at start, save every ``every_steps`` MPC steps and at shutdown.

    Call ``after_cycle`` once per answered cycle, after its frames are sent (outside the
    timed step). Save failures are counted and reported, never raised: learning continues.
    ``blocked_by`` (set after construction) names why the state must not be saved now, or
    returns None: a core that raised may have left its state half-updated, and saving it
    would carry the fault into the next start.
    """

    def __init__(self, path: str | Path, controller: Checkpointable, cfg_hash: str, *,
                 every_steps: int | None = None,
                 report: Callable[[str], None] | None = None,
                 limits: StateLimits | None = None) -> None:
        self.path = Path(path)
        self.limits = limits
        self.controller = controller
        self.cfg_hash = cfg_hash
        # default: every 1 s of controller time
        self.every_steps = max(1, int(every_steps) if every_steps else round(1.0 / controller.ts))
        self.report = report or (lambda _msg: None)
        self.steps = 0              # MPC steps learned since the cold start (incl. restored)
        self._since_save = 0
        self.saves = 0
        self.save_failures = 0
        self.last_error: str | None = None
        self.restore_result: RestoreResult | None = None
        self.blocked_by: Callable[[], str | None] = lambda: None
        self.blocked_saves = 0
        self.block_reason: str | None = None

    def restore(self) -> RestoreResult:
        """Remove stale temp files of crashed saves, then restore if the file matches."""
        directory = self.path.parent if str(self.path.parent) else Path(".")
        for stale in directory.glob(f".{self.path.name}.*.tmp"):
            with contextlib.suppress(OSError):
                stale.unlink()
        result = load_checkpoint(self.path, self.controller, cfg_hash=self.cfg_hash,
                                 limits=self.limits)
        self.steps = result.steps
        self.restore_result = result
        self.report(f"checkpoint: {result.reason}")
        return result

    def after_cycle(self, mpc_update: bool) -> bool:
        """Count an MPC step; save when ``every_steps`` have passed. True if it saved."""
        if not mpc_update:
            return False
        self.steps += 1
        self._since_save += 1
        if self._since_save < self.every_steps:
            return False
        return self.save()

    def save(self) -> bool:
        """Save now; False (counted and reported) if it failed or is blocked."""
        self._since_save = 0
        reason = self.blocked_by()
        if reason is not None:
            if self.blocked_saves == 0:
                self.report(f"checkpoint: not saved to {self.path} ({reason})")
            self.blocked_saves += 1
            self.block_reason = reason
            return False
        try:
            save_checkpoint(self.path, self.controller, cfg_hash=self.cfg_hash,
                            steps=self.steps)
        except Exception as exc:  # disk full, permissions...: keep controlling
            self.save_failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            self.report(f"checkpoint: save to {self.path} failed: {self.last_error}")
            return False
        self.saves += 1
        return True

    def summary(self) -> dict[str, Any]:
        """Counters for the process summary."""
        r = self.restore_result
        return {"path": str(self.path), "restored": bool(r and r.restored),
                "restore_reason": r.reason if r else None, "steps": self.steps,
                "saves": self.saves, "save_failures": self.save_failures,
                "last_error": self.last_error, "blocked_saves": self.blocked_saves,
                "block_reason": self.block_reason}
