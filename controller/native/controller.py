"""A controller whose step is the C core (the production path); same protocol, outputs,
counters and checkpoint state as the numpy reference (controller/core/mpc/controller.py).

The state lives in the extension object's ``rh_ctrl_t``; this class reads and writes it
through numpy views at offsets the binding reports (``Core.offsets()``), so checkpoints,
counters and diagnostics need no further C. ``copy.deepcopy`` gives a controller that runs on
bit for bit (the core relocates OSQP's internal pointers); ``pickle`` stores the
configuration and ``get_state()`` (the checkpoint contract: learned state, warm start and
references restored; OSQP's internal ρ and scaled iterates restart, as after a checkpoint).
"""

from __future__ import annotations

import copy
from types import ModuleType
from typing import Any

import numpy as np

from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.registry import ControllerConfig
from controller.native import layouts
from controller.native.backend import core_module
from controller.native.config import ctrl_config, uses_envelope, uses_grip_demand
from controller.native.layouts import RhEkfCounters


class _View:
    """Typed numpy views into a Core's state bytes."""

    def __init__(self, core: Any, real: np.dtype) -> None:
        self.buf = np.frombuffer(memoryview(core), dtype=np.uint8)
        self.off = core.offsets()
        self.real = real

    def arr(self, key: str, n: int, dtype: Any = None) -> np.ndarray:
        dt = np.dtype(self.real if dtype is None else dtype)
        o = self.off[key]
        return self.buf[o:o + n * dt.itemsize].view(dt)

    def struct(self, key: str, ctype: Any) -> Any:
        return ctype.from_buffer(self.buf, self.off[key])


class NativeGrip:
    """The grip estimate of the core (controller/core/grip.py's state): mu and the grip
    shown (-), the last saturation index (-) and grip in use (-)."""

    def __init__(self, v: _View) -> None:
        self._mu = v.arr("grip.mu", 1, np.float64)
        self._shown = v.arr("grip.shown", 1, np.float64)
        self._sat = v.arr("grip.saturation", 1, np.float64)
        self._used = v.arr("grip.grip_used", 1, np.float64)

    mu = property(lambda s: float(s._mu[0]))
    shown = property(lambda s: float(s._shown[0]))
    saturation = property(lambda s: float(s._sat[0]))
    grip_used = property(lambda s: float(s._used[0]))

    def get_state(self) -> dict[str, float]:
        """μ̂ and the grip shown, as GripEstimator.get_state."""
        return {"grip.mu": self.mu, "grip.shown": self.shown}

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore get_state()."""
        self._mu[0] = float(d.get("grip.mu", self._mu[0]))
        self._shown[0] = float(d.get("grip.shown", 0.0))


class NativeAllocator:
    """What the allocation exposes of its state: the motors' previous torques (N·m) and the
    count of allocations a wheel was held back by the motor torque rate."""

    def __init__(self, v: _View) -> None:
        self.prev = v.arr("alloc.prev", 4)
        self._calls = v.arr("alloc.rate_limited_calls", 1, np.int64)

    @property
    def rate_limited_calls(self) -> int:
        """Allocations in which a wheel was held back by the motor torque rate."""
        return int(self._calls[0])


class NativeQp:
    """What the MPC's QP exposes of its state (LinearizedMpc's counters and solution)."""

    backend = "native"

    def __init__(self, v: _View, n: int, m: int) -> None:
        self.N, self.m = n, m
        self.sol = v.arr("qp.sol", n)
        self._y = v.arr("qp.y_last", m, np.float64)
        self._has_y = v.arr("qp.has_y_last", 1, np.int32)
        self._c = {k: v.arr(f"qp.{k}", 1, np.int64) for k in (
            "last_iterations", "worst_iterations", "max_iter_hits", "fallbacks")}
        self._status = v.arr("qp.last_status", 1, np.int32)
        self.slack = v.arr("qp.slack", 2, np.float64)   # (s_r, s_α) of the envelope shape
        self.zprev = v.arr("qp.zprev", 1, np.float64)   # ΔM of the last solve, decision units

    last_iterations = property(lambda s: int(s._c["last_iterations"][0]))
    worst_iterations = property(lambda s: int(s._c["worst_iterations"][0]))
    max_iter_hits = property(lambda s: int(s._c["max_iter_hits"][0]))
    fallbacks = property(lambda s: int(s._c["fallbacks"][0]))
    last_status = property(lambda s: QpStatus(int(s._status[0])))

    def y_last(self) -> np.ndarray:
        """OSQP's last dual iterate (m,) (zeros before the first solve)."""
        return self._y.copy() if self._has_y[0] else np.zeros(self.m)


class _Counters:
    """EkfCounters-like view (``as_dict()`` and attributes) of rh_ekf_counters_t."""

    def __init__(self, c: RhEkfCounters) -> None:
        self._c = c

    def __getattr__(self, name: str) -> int:
        return int(getattr(self._c, name))

    def as_dict(self) -> dict[str, int]:
        return self._c.as_dict()


class NativeRhonnModel:
    """The RHONN model's learned state in the core (RhonnModel's names)."""

    nx = 3

    def __init__(self, v: _View, form: str) -> None:
        self.form = form
        key = "rhonn.ud" if form == "ud" else "rhonn.ekf"
        self.W = v.arr(f"{key}.W", 45).reshape(3, 15)
        if form == "ud":
            self._U = v.arr("rhonn.ud.U", 675).reshape(3, 15, 15)
            self._D = v.arr("rhonn.ud.D", 45).reshape(3, 15)
        else:
            self._P = v.arr("rhonn.ekf.P", 675).reshape(3, 15, 15)
        self.counters = _Counters(v.struct(f"{key}.counters", RhEkfCounters))
        self.rec_phi = v.arr("rhonn.model.rec_phi", 15)
        self.rec_chi = v.arr("rhonn.model.rec_chi", 3)
        self._has_record = v.arr("rhonn.model.has_record", 1, np.int32)
        self._err_ms = v.arr("rhonn.model.err_ms", 1)
        self._learn = v.arr("rhonn.model.learn_steps", 1, np.int64)
        self._gate = v.arr("rhonn.model.gate_open", 1, np.int32)

    def forget_record(self) -> None:
        """Drop the pending prediction (the node calls it when sensors recover)."""
        self._has_record[0] = 0

    @property
    def err_ms(self) -> float:
        """Filtered mean square of the one-step ωr prediction error, (rad/s)² (the gate's)."""
        return float(self._err_ms[0])

    @property
    def P(self) -> np.ndarray:
        """Weight covariances (3, 15, 15) (U D Uᵀ for the UD form)."""
        if self.form != "ud":
            return self._P.astype(float)
        U, D = self._U.astype(float), self._D.astype(float)
        return np.einsum("nij,nj,nkj->nik", U, D, U)

    def get_state(self) -> dict[str, np.ndarray | float]:
        return {"rhonn.W": self.W.astype(float), "rhonn.P": self.P,
                "rhonn.rec_phi": self.rec_phi.astype(float),
                "rhonn.rec_chi": self.rec_chi.astype(float),
                "rhonn.has_record": float(self._has_record[0]),
                "rhonn.err_ms": float(self._err_ms[0]),
                "rhonn.learn_steps": float(self._learn[0]),
                "rhonn.gate_open": float(self._gate[0])}

    def set_state(self, d: dict[str, Any]) -> None:
        self.W[:] = np.asarray(d["rhonn.W"])
        P = np.asarray(d["rhonn.P"], dtype=float)
        if self.form == "ud":
            for i in range(3):
                self._U[i], self._D[i] = _ud_factor(P[i])
        else:
            self._P[:] = P
        self.rec_phi[:] = np.asarray(d["rhonn.rec_phi"])
        self.rec_chi[:] = np.asarray(d["rhonn.rec_chi"])
        self._has_record[0] = int(bool(d["rhonn.has_record"]))
        self._err_ms[0] = float(d.get("rhonn.err_ms", self._err_ms[0]))
        self._learn[0] = int(d.get("rhonn.learn_steps", 0))
        self._gate[0] = int(bool(d.get("rhonn.gate_open", 0.0)))


def _ud_factor(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = U D Uᵀ with U unit upper triangular (the UD EKF's set_state)."""
    n = P.shape[0]
    P = 0.5 * (P + P.T)
    U = np.eye(n)
    D = np.zeros(n)
    for j in range(n - 1, -1, -1):
        D[j] = P[j, j] - np.sum(D[j + 1:] * U[j, j + 1:] ** 2)
        for i in range(j):
            U[i, j] = (P[i, j] - np.sum(D[j + 1:] * U[i, j + 1:] * U[j, j + 1:])) / D[j]
    return U, D


class NativeReferences:
    """The reference generator's state in the core (counters by their Python names)."""

    def __init__(self, v: _View, float32: bool) -> None:
        self._st = v.struct("rhonn.refs", layouts.refs_types(float32).Refs)

    rounds_last = property(lambda s: int(s._st.alg1.rounds_last))
    not_converged = property(lambda s: int(s._st.alg1.not_converged))
    active_calls = property(lambda s: int(s._st.guard.active_calls))

    def get_state(self) -> dict[str, np.ndarray | float]:
        return layouts.get_state(self._st)

    def set_state(self, d: dict[str, Any]) -> None:
        layouts.set_state(self._st, d)


class NativeGripDemand:
    """The grip-limited demand in the core (references/grip_demand.py's diagnostics, and the
    sideslip guard's around it when configured): the last limit factor and share of
    Algorithm 1's steady state (-), the guard's active calls; Algorithm 1's counters and
    state (its fixed point, ``fixed_point``) when its share is > 0, as GripDemandReferences
    exposes them."""

    def __init__(self, v: _View, fixed_point: NativeReferences | None) -> None:
        self._factor = v.arr("gdemand.factor_last", 1, np.float64)
        self._weight = v.arr("gdemand.weight_last", 1, np.float64)
        self._active = v.arr("gdemand.guard.active_calls", 1, np.int32)
        self.fixed_point = fixed_point

    factor_last = property(lambda s: float(s._factor[0]))
    weight_last = property(lambda s: float(s._weight[0]))
    active_calls = property(lambda s: int(s._active[0]))
    not_converged = property(
        lambda s: s.fixed_point.not_converged if s.fixed_point is not None else 0)
    rounds_last = property(
        lambda s: s.fixed_point.rounds_last if s.fixed_point is not None else 0)

    def get_state(self) -> dict[str, np.ndarray | float]:
        return self.fixed_point.get_state() if self.fixed_point is not None else {}

    def set_state(self, d: dict[str, Any]) -> None:
        if self.fixed_point is not None:
            self.fixed_point.set_state(d)


class NativeController:
    """Controller protocol on the C core (see the module docstring)."""

    def __init__(self, name: str, cfg: ControllerConfig, module: ModuleType) -> None:
        self.name = name
        self.params = cfg.params
        self.ts = float(cfg.ts)
        self.v_min = float(cfg.v_min)
        self.backend = "native"
        self._cfg = cfg
        self._module = module
        self.out = ControllerOutputs()
        self._core = module.Core(bytes(ctrl_config(name, cfg)), self.out)
        self._bind()

    def _bind(self) -> None:
        core = self._core
        float32 = core.sizes()[2] == 4
        self.dtype = np.float32 if float32 else np.float64
        v = _View(core, np.dtype(self.dtype))
        self._v = v
        self.step = core.step              # the hot path: one C call
        self.allocate_only = core.allocate_only
        self._scal = {k: v.arr(k, 1, dt) for k, dt in (
            ("dm_held", self.dtype), ("dm_prev", self.dtype), ("confidence", self.dtype),
            ("steps", np.int64), ("invalid_steps", np.int64))}
        self.allocator = NativeAllocator(v)
        self.grip = NativeGrip(v) if (uses_grip_demand(self.name, self._cfg)
                                      or uses_envelope(self.name, self._cfg)) else None
        self.qp: NativeQp | None = None
        self.model: NativeRhonnModel | None = None
        self.references: NativeReferences | NativeGripDemand | None = None
        if self.name != "passive":
            self.qp = NativeQp(v, int(v.arr("qp.N", 1, np.int32)[0]),
                               int(v.arr("qp.m", 1, np.int32)[0]))
        if self.name == "nmpc-rhonn":
            self.model = NativeRhonnModel(v, self._cfg.rhonn.ekf.form)
        if uses_grip_demand(self.name, self._cfg):
            # Algorithm 1 (the refs module) is the demand's fixed point when its share is > 0
            share = self.name == "nmpc-rhonn" and self._cfg.handling.fixed_point_share > 0.0
            self.references = NativeGripDemand(v, NativeReferences(v, float32) if share
                                               else None)
        elif self.name == "nmpc-rhonn" and self._cfg.references.kind != "linear":
            self.references = NativeReferences(v, float32)   # the linear design keeps none

    # ------------------------------------------------------------------ protocol
    def step(self, inputs: ControllerInputs) -> ControllerOutputs:  # replaced in _bind
        return self._core.step(inputs)

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:  # replaced
        return self._core.allocate_only(inputs)

    def reset(self) -> None:
        """Cold start: weights, filters, references, warm starts, outputs."""
        self._core.reset()

    dm_held = property(lambda s: float(s._scal["dm_held"][0]))
    dm_prev = property(lambda s: float(s._scal["dm_prev"][0]))
    confidence = property(lambda s: float(s._scal["confidence"][0]))
    steps = property(lambda s: int(s._scal["steps"][0]))
    invalid_steps = property(lambda s: int(s._scal["invalid_steps"][0]))

    # ------------------------------------------------------------------ checkpoint
    def get_state(self) -> dict[str, np.ndarray | float]:
        """Learned/warm state (the keys of MpcController.get_state)."""
        if self.name == "passive":
            return {"alloc.prev": self.allocator.prev.astype(float)}
        d: dict[str, Any] = {"alloc.prev": self.allocator.prev.astype(float)}
        for part in (self.model, self.references, self.grip):
            if part is not None:
                d.update(part.get_state())
        d["qp.sol"] = self.qp.sol.astype(float)
        d["qp.y"] = self.qp.y_last()
        d["qp.zprev"] = float(self.qp.zprev[0])
        if uses_envelope(self.name, self._cfg):
            d["qp.slack"] = self.qp.slack.astype(float)
        d["ctrl.dm_held"] = self.dm_held
        d["ctrl.dm_prev"] = self.dm_prev
        o = self.out
        d["ctrl.refs"] = np.array([o.yaw_rate_ref, o.vy_ref, o.beta_ref])
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state(); OSQP is warm-started from (sol, y)."""
        self.allocator.prev[:] = np.asarray(d.get("alloc.prev", np.zeros(4)), dtype=float)
        if self.name == "passive":
            return
        for part in (self.model, self.references, self.grip):
            if part is not None:
                part.set_state(d)
        sol = np.asarray(d["qp.sol"], dtype=float)
        self.qp.sol[:] = sol
        if uses_envelope(self.name, self._cfg):   # the slacks' warm start (rh_qp_warm_start)
            self.qp.slack[:] = np.asarray(d.get("qp.slack", np.zeros(2)), dtype=float)
        self.qp.zprev[0] = float(d.get("qp.zprev", 0.0))
        y = np.asarray(d.get("qp.y", np.zeros(self.qp.m)), dtype=float)
        self._core.warm_start(np.ascontiguousarray(sol / self._cfg.mpc.u_scale),
                              np.ascontiguousarray(y))
        self._scal["dm_held"][0] = float(d["ctrl.dm_held"])
        self._scal["dm_prev"][0] = float(d["ctrl.dm_prev"])
        refs = np.asarray(d["ctrl.refs"], dtype=float)
        v = self._v
        out_off = v.off["out"]
        # rh_outputs_t: torques[4], total_torque, delta_m, yaw_rate_ref, vy_ref, beta_ref
        r = v.buf[out_off:out_off + 9 * v.real.itemsize].view(v.real)
        r[6:9] = refs
        self.out.yaw_rate_ref, self.out.vy_ref, self.out.beta_ref = (float(x) for x in refs)

    # ------------------------------------------------------------------ copies
    def __deepcopy__(self, memo: dict[int, Any]) -> NativeController:
        new = NativeController.__new__(NativeController)
        memo[id(self)] = new
        new.__dict__.update({k: v for k, v in self.__dict__.items()
                             if k in ("name", "params", "ts", "v_min", "backend", "_module")})
        new._cfg = copy.deepcopy(self._cfg, memo)
        new.out = copy.deepcopy(self.out, memo)
        new._core = self._module.Core(bytes(ctrl_config(self.name, new._cfg)), new.out)
        new._core.copy_from(self._core)
        new._bind()
        return new

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (self.name, self._cfg, self.dtype == np.float32, self.get_state(),
                           self.out))


def _rebuild(name: str, cfg: ControllerConfig, float32: bool, state: dict[str, Any],
             out: ControllerOutputs) -> NativeController:
    module = core_module(float32)
    if module is None:
        raise RuntimeError("the C core is not built here: cannot restore a native controller")
    c = NativeController(name, cfg, module)
    c.set_state(state)
    for k in ("total_torque", "delta_m", "qp_status", "qp_iterations", "fallback"):
        setattr(c.out, k, getattr(out, k))
    c.out.torques[:] = out.torques
    c.out.model_prediction[:] = out.model_prediction
    return c
