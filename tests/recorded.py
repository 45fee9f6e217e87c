"""Recorded closed-loop inputs and helpers to replay them (shared by the tests that compare
controllers step by step: the numpy reference, the C core, copies and restores)."""

from __future__ import annotations

import math
import time
from importlib import resources
from pathlib import Path
from typing import Any

import can
import numpy as np

from controller.core.interfaces import ControllerInputs
from controller.registry import make_controller
from harness.bench.controller_step import recorded_inputs as recorded_inputs  # re-export
from harness.bench.controller_step import set_toml_keys
from harness.run.bus_logger import BusRecorder

OUT_COLS = ("T1", "T2", "T3", "T4", "dM", "r_ref", "vy_ref", "pred_vx", "pred_vy", "pred_r")


def config_file(tmp: Path, mpc: str = "", ekf: str = "") -> str:
    """default.toml with extra lines in [mpc] and [rhonn.ekf], written to tmp."""
    text = resources.files("controller").joinpath("config/default.toml").read_text()
    text = set_toml_keys(text, "[mpc]", mpc)
    text = set_toml_keys(text, "[rhonn.ekf]", ekf)
    path = tmp / f"c{abs(hash(mpc + ekf))}.toml"
    path.write_text(text)
    return str(path)


def replay(name: str, path: str, rec: list[ControllerInputs],
           backend: str | None = None) -> np.ndarray:
    """Outputs (steps, 10) (OUT_COLS) of a fresh controller stepped on the recorded inputs."""
    c = make_controller(name, path, backend=backend)
    rows = []
    for inp in rec:
        o = c.step(inp)
        rows.append([*o.torques, o.delta_m, o.yaw_rate_ref, o.vy_ref, *o.model_prediction])
    return np.array(rows, dtype=float)


def _copy(inp: ControllerInputs) -> ControllerInputs:
    out = ControllerInputs(**{k: getattr(inp, k) for k in ControllerInputs.__slots__})
    out.wheel_speeds = np.array(inp.wheel_speeds, dtype=float)
    return out


def awkward_inputs(rec: list[ControllerInputs], absurd: bool = True) -> list[ControllerInputs]:
    """The recorded inputs with edge cases spliced in after the controller acted (absurd:
    also a finite Vy of 1e200, which makes the QP data unusable and drives the EKF's
    weights to their bound)."""
    seq = [_copy(i) for i in rec]
    k = 150

    def at(j: int, **kw: Any) -> None:
        inp = _copy(seq[j])
        for name, v in kw.items():
            setattr(inp, name, v)
        seq.insert(j, inp)

    at(k, vy=math.nan)                              # non-finite input
    at(k + 3, sensors_valid=False)                  # invalid frames
    at(k + 5, yaw_rate=math.inf, sensors_valid=False)
    at(k + 8, vx=2.0)                               # below v_min: no QP
    at(k + 11, stab_enable=False)                   # stability function off
    at(k + 14, vx=1e200)                            # finite, absurd
    if absurd:
        at(k + 15, vy=1e200)                        # → QP data unusable: fallback
    at(k + 17, accel_pedal=math.nan, brake_pedal=0.3)
    at(k + 20, swa_rad=math.nan)
    ws_list = _copy(seq[k + 23])
    ws_list.wheel_speeds = [float(v) for v in ws_list.wheel_speeds]  # not a float64 array
    seq.insert(k + 23, ws_list)
    return seq


def state_of(c: Any) -> dict[str, Any]:
    """Outputs, counters and learned state of a numpy-reference MpcController, as plain
    values."""
    o, qp, al = c.out, c.qp, c.allocator
    d: dict[str, Any] = {
        "out": [*o.torques.tolist(), o.total_torque, o.delta_m, o.yaw_rate_ref, o.vy_ref,
                o.beta_ref, o.qp_status, o.qp_iterations, o.fallback,
                *o.model_prediction.tolist()],
        "ctrl": [c.steps, c.invalid_steps, float(c.dm_held), float(c.dm_prev),
                 float(c.confidence)],
        "qp": [qp.max_iter_hits, qp.fallbacks, qp.worst_iterations, qp.last_iterations,
               int(qp.last_status), float(qp._lo_last), float(qp._hi_last),
               *qp.sol.tolist(), *qp.l.tolist(), *qp.u.tolist()],
        "alloc": [float(al.tt_applied), float(al.dm_applied), *al.limits.tolist(),
                  *al.prev.tolist(), al.rate_limited_calls],
    }
    m = c.model
    if hasattr(m, "ekf"):
        r = c.references
        inner = getattr(r, "inner", r)
        fp, dem = inner.fixed_point, getattr(inner, "demand", None)
        d["rhonn"] = [m.err_ms, m.learn_steps, m._gate_open, m._has_record,
                      *m.ekf.counters.as_dict().values(), getattr(m.ekf, "_since_eig", 0)]
        d["refs"] = [getattr(r, "active_calls", 0), inner.not_converged, inner.weight_last,
                     fp.rounds_last, fp.cost_last, fp.ay_envelope]
        d["refs"] += ([dem.ay_envelope, dem._dw_prev] if dem is not None
                      else [inner.factor_last])
    if getattr(c, "grip", None) is not None:
        d["grip"] = [c.grip.mu, c.grip.shown, c.grip.saturation, c.grip.grip_used,
                     *qp.slack.tolist()]
    for k, v in c.get_state().items():
        d["state." + k] = np.asarray(v, dtype=float).ravel().tolist()
    return d


def record_over_virtual_bus(path: Path, frames: list[can.Message], channel: str
                            ) -> BusRecorder:
    """``frames`` sent one by one on a python-can virtual bus (as on SocketCAN), recorded by
    the harness's lockstep recorder into ``path``; returns the (stopped) recorder."""
    rec = BusRecorder(f"virtual:{channel}", path, stamp="sim").start()
    with can.Bus(channel=channel, interface="virtual") as sender:
        for f in frames:
            sender.send(f)
        deadline = time.monotonic() + 60.0  # a loaded machine may starve the thread a while
        while rec.frames < len(frames) and time.monotonic() < deadline:
            time.sleep(0.05)
    rec.stop()
    return rec
