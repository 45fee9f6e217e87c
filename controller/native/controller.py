"""A controller whose step is the C core (the production path); same protocol, outputs,
counters and checkpoint state as the numpy reference (controller/core/mpc/controller.py).

The state is the ``rh_ctrl_t`` of one ``Stepper`` (the step path cdef_gen.py generates
from the headers: ``step``/``allocate_only`` are its methods, one C call each), reached
through the cffi binding generated from the same headers: fields are read and written by
their C names, arrays through numpy views of the struct's memory, so checkpoints, counters
and diagnostics need no further C and no layout is written in Python. ``copy.deepcopy``
gives a controller that runs on bit for bit (the core relocates OSQP's internal pointers);
``pickle`` stores the configuration and ``get_state()`` (the checkpoint contract: learned
state, warm start and references restored; OSQP's internal ρ and scaled iterates restart, as
after a checkpoint).
"""

from __future__ import annotations

import copy
import math
from types import ModuleType
from typing import Any, ClassVar

import numpy as np

from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.registry import ControllerConfig
from controller.native.backend import core_module
from controller.native.config import ctrl_config, uses_envelope, uses_grip_demand


class ArrayView:
    """numpy views of C array fields of one binding (a cffi module: the core's, or a module
    build of the back-to-back tests): the struct's memory, no copy."""

    _DTYPES: ClassVar[dict[str, Any]] = {"double": np.float64, "float": np.float32,
                                         "int": np.intc, "int64_t": np.int64}

    def __init__(self, module: ModuleType) -> None:
        self.ffi = module.ffi
        self.lib = module.lib

    def arr(self, cdata: Any) -> np.ndarray:
        """A writable numpy view of a C array (its element type from the C type)."""
        dt = self._DTYPES[self.ffi.typeof(cdata).item.cname]
        return np.frombuffer(self.ffi.buffer(cdata), dtype=dt)


class NativeGrip:
    """The grip estimate of the core (controller/core/grip.py's state): mu and the grip
    shown (-), the last saturation index (-) and grip in use (-)."""

    def __init__(self, c: Any) -> None:
        self._g = c.grip     # rh_grip_t

    mu = property(lambda s: float(s._g.mu))
    shown = property(lambda s: float(s._g.shown))
    saturation = property(lambda s: float(s._g.saturation))
    grip_used = property(lambda s: float(s._g.grip_used))

    def get_state(self) -> dict[str, float]:
        """μ̂ and the grip shown, as GripEstimator.get_state."""
        return {"grip.mu": self.mu, "grip.shown": self.shown}

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore get_state()."""
        self._g.mu = float(d.get("grip.mu", self._g.mu))
        self._g.shown = float(d.get("grip.shown", 0.0))


class NativeAllocator:
    """What the allocation exposes of its state: the motors' previous torques (N·m) and the
    count of allocations a wheel was held back by the motor torque rate."""

    def __init__(self, v: ArrayView, c: Any) -> None:
        self._a = c.alloc    # rh_alloc_t
        self.prev = v.arr(c.alloc.prev)

    @property
    def rate_limited_calls(self) -> int:
        """Allocations in which a wheel was held back by the motor torque rate."""
        return int(self._a.rate_limited_calls)


class NativeQp:
    """What the MPC's QP exposes of its state (LinearizedMpc's counters and solution)."""

    backend = "native"

    def __init__(self, v: ArrayView, c: Any) -> None:
        q = self._q = c.qp   # rh_qp_t
        self.N, self.m = int(q.N), int(q.m)
        self.sol = v.arr(q.sol)[:self.N]
        self._y = v.arr(q.y_last)[:self.m]
        self.slack = v.arr(q.slack)   # (s_r, s_α) of the envelope shape
        # the last QP data built (LinearizedMpc's names): P's upper triangle in CSC order
        # and q, decision units (ΔM / u_scale)
        self.Px = v.arr(q.Px)[:self.N * (self.N + 1) // 2]
        self.q = v.arr(q.q)[:self.N]

    last_iterations = property(lambda s: int(s._q.last_iterations))
    worst_iterations = property(lambda s: int(s._q.worst_iterations))
    max_iter_hits = property(lambda s: int(s._q.max_iter_hits))
    fallbacks = property(lambda s: int(s._q.fallbacks))
    unconstrained_solves = property(lambda s: int(s._q.unconstrained_solves))
    last_status = property(lambda s: QpStatus(int(s._q.last_status)))

    @property
    def zprev(self) -> float:
        """ΔM applied at the last solve, decision units (the jerk weight's z₋₂ next step)."""
        return float(self._q.zprev)

    @zprev.setter
    def zprev(self, value: float) -> None:
        self._q.zprev = float(value)

    def y_last(self) -> np.ndarray:
        """OSQP's last dual iterate (m,) (zeros before the first solve)."""
        return self._y.astype(float) if self._q.has_y_last else np.zeros(self.m)


class _Counters:
    """EkfCounters-like view (``as_dict()`` and attributes) of rh_ekf_counters_t."""

    def __init__(self, ffi: Any, c: Any) -> None:
        self._c = c
        self._names = [n for n, _ in ffi.typeof(c).fields]

    def __getattr__(self, name: str) -> int:
        return int(getattr(self._c, name))

    def as_dict(self) -> dict[str, int]:
        return {n: int(getattr(self._c, n)) for n in self._names}


class NativeRhonnModel:
    """The RHONN model's learned state in the core (RhonnModel's names)."""

    nx = 3

    def __init__(self, v: ArrayView, c: Any, form: str) -> None:
        self.form = form
        m = self._m = c.u.rhonn.model   # rh_rhonn_model_t
        f = m.f.ud if form == "ud" else m.f.std
        self.W = v.arr(f.W).reshape(3, 15)
        if form == "ud":
            self._U = v.arr(f.U).reshape(3, -1)   # strictly upper parts, packed (ud_ekf.h)
            self._D = v.arr(f.D).reshape(3, 15)
        else:
            self._P = v.arr(f.P).reshape(3, 15, 15)
        self.counters = _Counters(v.ffi, f.counters)
        self.rec_phi = v.arr(m.rec_phi)
        self.rec_chi = v.arr(m.rec_chi)
        self._v = v
        # the learned ΔM effectiveness: its joint filter with the yaw row (yaw_gain.h)
        self.dm_gain_on = bool(m.dm_gain_on)
        g = m.dm_gain
        self._gW = v.arr(g.W).reshape(1, 16)
        self._gM = v.arr(g.PU).reshape(1, 16, 16)   # P, or U in the UD form
        self._gD = v.arr(g.D).reshape(1, 16)

    @property
    def theta(self) -> float:
        """The ΔM effectiveness in use, - (1: off or the nominal gain)."""
        return float(self._m.theta)

    def _gain_P(self) -> np.ndarray:
        """The joint filter's covariance (1, 16, 16), float64 (U D Uᵀ in the UD form)."""
        if self.form != "ud":
            return self._gM.astype(float)
        U, D = self._gM.astype(float), self._gD.astype(float)
        return np.einsum("nij,nj,nkj->nik", U, D, U)

    def forget_record(self) -> None:
        """Drop the pending prediction (the node calls it when sensors recover)."""
        self._m.has_record = 0

    @property
    def err_ms(self) -> float:
        """Filtered mean square of the one-step ωr prediction error, (rad/s)² (the gate's)."""
        return float(self._m.err_ms)

    @property
    def P(self) -> np.ndarray:
        """Weight covariances (3, 15, 15) (U D Uᵀ for the UD form)."""
        if self.form != "ud":
            return self._P.astype(float)
        U, D = unpack_ud_factor(self._U.astype(float), 15), self._D.astype(float)
        return np.einsum("nij,nj,nkj->nik", U, D, U)

    def get_state(self) -> dict[str, np.ndarray | float]:
        m = self._m
        return {"rhonn.W": self.W.astype(float), "rhonn.P": self.P,
                "rhonn.rec_phi": self.rec_phi.astype(float),
                "rhonn.rec_chi": self.rec_chi.astype(float),
                "rhonn.has_record": float(m.has_record),
                "rhonn.err_ms": float(m.err_ms),
                "rhonn.learn_steps": float(m.learn_steps),
                "rhonn.gate_open": float(m.gate_open),
                **({"rhonn.dm_gain.W": self._gW.astype(float), "rhonn.dm_gain.P": self._gain_P(),
                    "rhonn.rec_u": float(m.rec_u)} if self.dm_gain_on else {})}

    def set_state(self, d: dict[str, Any]) -> None:
        self.W[:] = np.asarray(d["rhonn.W"])
        P = np.asarray(d["rhonn.P"], dtype=float)
        if self.form == "ud":
            for i in range(3):
                U, self._D[i] = _ud_factor(P[i])
                self._U[i] = pack_ud_factor(U)
        else:
            self._P[:] = P
        m = self._m
        self.rec_phi[:] = np.asarray(d["rhonn.rec_phi"])
        self.rec_chi[:] = np.asarray(d["rhonn.rec_chi"])
        m.has_record = int(bool(d["rhonn.has_record"]))
        m.err_ms = float(d.get("rhonn.err_ms", m.err_ms))
        m.learn_steps = int(d.get("rhonn.learn_steps", 0))
        m.gate_open = int(bool(d.get("rhonn.gate_open", 0.0)))
        if self.dm_gain_on and "rhonn.dm_gain.W" in d:
            self._gW[:] = np.asarray(d["rhonn.dm_gain.W"]).reshape(1, 16)
            P = np.asarray(d["rhonn.dm_gain.P"], dtype=float).reshape(1, 16, 16)
            if self.form == "ud":
                self._gM[0], self._gD[0] = _ud_factor(P[0])
            else:
                self._gM[:] = P
            m.rec_u = float(d.get("rhonn.rec_u", 0.0))
        # the ΔM gains from the restored θ (θ = 1 when off)
        self._v.lib.rh_rhonn_model_sync_dm_gain(self._v.ffi.addressof(m))


def _packed_positions(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of an n × n factor's strictly upper entries in the C core's packed
    order (ud_ekf.h RH_UD_AT: by columns, entry (a, j) at j (j − 1) / 2 + a)."""
    cols = np.concatenate([np.full(j, j) for j in range(1, n)])
    rows = np.concatenate([np.arange(j) for j in range(1, n)])
    return rows, cols


def unpack_ud_factor(packed: np.ndarray, n: int) -> np.ndarray:
    """The unit upper triangular factors (..., n, n) from the core's packed strictly upper
    parts (..., n (n − 1) / 2)."""
    rows, cols = _packed_positions(n)
    U = np.broadcast_to(np.eye(n), (*packed.shape[:-1], n, n)).copy()
    U[..., rows, cols] = packed
    return U


def pack_ud_factor(U: np.ndarray) -> np.ndarray:
    """The core's packed strictly upper parts (..., n (n − 1) / 2) of factors (..., n, n)."""
    rows, cols = _packed_positions(U.shape[-1])
    return U[..., rows, cols]


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
    """The reference generator's state in the core (counters by their Python names; the
    get_state keys of references/algorithm1.py, intent.py and slow_weights.py; the sideslip
    guard is memoryless)."""

    def __init__(self, v: ArrayView, refs: Any) -> None:
        self._st = refs   # rh_refs_t (in the core: rh_ctrl_t's u.rhonn.refs)
        self._lib = v.lib
        self._v = v

    rounds_last = property(lambda s: int(s._st.alg1.rounds_last))
    not_converged = property(lambda s: int(s._st.alg1.not_converged))
    active_calls = property(lambda s: int(s._st.guard.active_calls))

    def _kinds(self) -> tuple[bool, bool, bool]:
        """(Algorithm 1's state, the intent design's, the bicycle demand's) in use."""
        k, lib = int(self._st.kind), self._lib
        return (k in (lib.RH_REFS_ALGORITHM1, lib.RH_REFS_BLEND, lib.RH_REFS_DEMAND),
                k in (lib.RH_REFS_INTENT, lib.RH_REFS_BLEND), k == lib.RH_REFS_DEMAND)

    def _w_get(self, s: Any, key: str) -> dict[str, np.ndarray | float]:
        return {key: self._v.arr(s.copy).astype(float).reshape(3, -1),
                f"{key}_started": float(s.started)}

    def _w_set(self, s: Any, key: str, d: dict[str, Any]) -> None:
        if key in d:
            self._v.arr(s.copy)[:] = np.asarray(d[key], dtype=float).ravel()
            s.started = int(bool(d.get(f"{key}_started", 1.0)))
        else:   # SlowWeights.set_state without the key: restart the copy
            s.started = 0

    def get_state(self) -> dict[str, np.ndarray | float]:
        st, d = self._st, {}
        alg1, intent, demand = self._kinds()
        if alg1:
            d["ref.ay_envelope"] = float(st.alg1.ay_envelope)
            d.update(self._w_get(st.alg1.weights, "ref.w_slow"))
        if intent:
            d.update(self._w_get(st.intent.weights, "ref.intent.w_slow"))
            d["ref.intent.ay_envelope"] = float(st.intent.ay_envelope)
            d["ref.intent.dw_prev"] = float(st.intent.dw_prev)
        if demand:
            d["ref.demand.ay_envelope"] = float(st.demand.ay_envelope)
            d["ref.demand.dw_prev"] = float(st.demand.dw_prev)
        return d

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore get_state() (defaults of the Python set_state for the keys those treat as
        optional; "ref.ay_envelope" is required as in RhonnReferences)."""
        st = self._st
        alg1, intent, demand = self._kinds()
        if alg1:
            st.alg1.ay_envelope = float(d["ref.ay_envelope"])
            self._w_set(st.alg1.weights, "ref.w_slow", d)
        if intent:
            self._w_set(st.intent.weights, "ref.intent.w_slow", d)
            st.intent.ay_envelope = float(d.get("ref.intent.ay_envelope", 0.0))
            st.intent.dw_prev = float(d.get("ref.intent.dw_prev", math.nan))
        if demand:
            st.demand.ay_envelope = float(d.get("ref.demand.ay_envelope", 0.0))
            st.demand.dw_prev = float(d.get("ref.demand.dw_prev", math.nan))


class NativeGripDemand:
    """The grip-limited demand in the core (references/grip_demand.py's diagnostics, and the
    sideslip guard's around it when configured): the last limit factor and share of
    Algorithm 1's steady state (-), the guard's active calls; Algorithm 1's counters and
    state (its fixed point, ``fixed_point``) when its share is > 0, as GripDemandReferences
    exposes them."""

    def __init__(self, c: Any, fixed_point: NativeReferences | None) -> None:
        self._g = c.gdemand   # rh_grip_demand_t
        self.fixed_point = fixed_point

    factor_last = property(lambda s: float(s._g.factor_last))
    weight_last = property(lambda s: float(s._g.weight_last))
    active_calls = property(lambda s: int(s._g.guard.active_calls))
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

    def __init__(self, name: str, cfg: ControllerConfig, module: ModuleType,
                 config: Any = None) -> None:
        """``config``: an ``rh_ctrl_config_t *`` of ``module`` to start from instead of the
        one ``cfg`` makes (the core's own checks are tested through it)."""
        self.name = name
        self.params = cfg.params
        self.ts = float(cfg.ts)
        self.v_min = float(cfg.v_min)
        self.backend = "native"
        self._cfg = cfg
        self._module = module
        self.out = ControllerOutputs()
        self._init_core(config)
        self._bind()

    def _init_core(self, config: Any = None) -> None:
        """A fresh rh_ctrl_t from the configuration (ValueError when rh_ctrl_init refuses)."""
        ffi, lib = self._module.ffi, self._module.lib
        # the state lives in the step path's object (cdef_gen.py); cffi's view keeps it alive
        self._stepper = self._module.Stepper(self.out)
        self._c = ffi.from_buffer("rh_ctrl_t *", self._stepper, require_writable=True)
        if config is None:
            config = ctrl_config(self.name, self._cfg, self._module)
        rc = lib.rh_ctrl_init(self._c, config)
        if rc == -2:
            raise ValueError(f"no generated QP solver for this horizon/shape in this build "
                             f"(horizon 1..{lib.RH_N_MAX})")
        if rc != 0:
            raise ValueError(f"invalid controller configuration (code {rc})")

    def _bind(self) -> None:
        c = self._c
        v = ArrayView(self._module)
        self._v = v
        self.dtype = np.float32 if v.ffi.sizeof("real_t") == 4 else np.float64
        # the step path: one C call from the inputs object into self.out (cdef_gen.py)
        self.step = self._stepper.step
        self.allocate_only = self._stepper.allocate_only
        self.allocator = NativeAllocator(v, c)
        self.grip = NativeGrip(c) if (uses_grip_demand(self.name, self._cfg)
                                      or uses_envelope(self.name, self._cfg)) else None
        self.qp: NativeQp | None = None
        self.model: NativeRhonnModel | None = None
        self.references: NativeReferences | NativeGripDemand | None = None
        if self.name != "passive":
            self.qp = NativeQp(v, c)
        if self.name == "nmpc-rhonn":
            self.model = NativeRhonnModel(v, c, self._cfg.rhonn.ekf.form)
        if uses_grip_demand(self.name, self._cfg):
            # Algorithm 1 (the refs module) is the demand's fixed point when its share is > 0
            share = self.name == "nmpc-rhonn" and self._cfg.handling.fixed_point_share > 0.0
            fixed_point = NativeReferences(v, c.u.rhonn.refs) if share else None
            self.references = NativeGripDemand(c, fixed_point)
        elif self.name == "nmpc-rhonn" and self._cfg.references.kind != "linear":
            self.references = NativeReferences(v, c.u.rhonn.refs)   # linear: none kept

    # ------------------------------------------------------------------ the step
    def step(self, inputs: ControllerInputs) -> ControllerOutputs:  # replaced in _bind
        """One MPC period; fills and returns ``self.out``. Bad values never raise: a missing
        or non-numeric number reads as NaN, a flag as its truth value (False when
        unreadable), unusable wheel speeds as zeros (the core then rejects the step)."""
        return self._stepper.step(inputs)

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:  # replaced
        """Re-allocate the held ΔM with the fresh pedal torque (between MPC periods)."""
        return self._stepper.allocate_only(inputs)

    def reset(self) -> None:
        """Cold start: weights, filters, references, warm starts, outputs."""
        self._module.lib.rh_ctrl_reset(self._c)

    dm_held = property(lambda s: float(s._c.dm_held))
    dm_prev = property(lambda s: float(s._c.dm_prev))
    confidence = property(lambda s: float(s._c.confidence))
    steps = property(lambda s: int(s._c.steps))
    invalid_steps = property(lambda s: int(s._c.invalid_steps))

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
        d["qp.zprev"] = self.qp.zprev
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
        self.qp.zprev = float(d.get("qp.zprev", 0.0))
        y = np.asarray(d.get("qp.y", np.zeros(self.qp.m)), dtype=float)
        self.warm_start(sol / self._cfg.mpc.u_scale, y)
        c = self._c
        c.dm_held, c.dm_prev = float(d["ctrl.dm_held"]), float(d["ctrl.dm_prev"])
        refs = [float(x) for x in np.asarray(d["ctrl.refs"], dtype=float)]
        c.out.yaw_rate_ref, c.out.vy_ref, c.out.beta_ref = refs
        self.out.yaw_rate_ref, self.out.vy_ref, self.out.beta_ref = (
            float(c.out.yaw_rate_ref), float(c.out.vy_ref), float(c.out.beta_ref))

    def warm_start(self, x: np.ndarray | None, y: np.ndarray | None) -> None:
        """OSQP warm start from x (N,) and y (m,), decision units (None = unchanged);
        ValueError for a wrong length."""
        if self.qp is None:
            return
        ffi = self._module.ffi
        args = []
        for label, a, n in (("x", x, self.qp.N), ("y", y, self.qp.m)):
            if a is None:
                args.append(ffi.NULL)
                continue
            a = np.ascontiguousarray(a, dtype=np.float64)
            if a.shape != (n,):
                raise ValueError(f"{label}: expected {n} float64")
            args.append(ffi.cast("OSQPFloat *", ffi.from_buffer(a)))
        self._module.lib.rh_qp_warm_start(ffi.addressof(self._c.qp), *args)

    # ------------------------------------------------------------------ copies
    def __deepcopy__(self, memo: dict[int, Any]) -> NativeController:
        new = NativeController.__new__(NativeController)
        memo[id(self)] = new
        new.__dict__.update({k: v for k, v in self.__dict__.items()
                             if k in ("name", "params", "ts", "v_min", "backend", "_module")})
        new._cfg = copy.deepcopy(self._cfg, memo)
        new.out = copy.deepcopy(self.out, memo)
        new._init_core()
        self._module.lib.rh_ctrl_copy(new._c, self._c)
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
