"""The MPC step as one compiled call, or two around the OSQP round (issue 13).

``MpcController.step`` (mpc/controller.py) stays the readable reference and the generic
path. ``build_compiled_step`` returns a ``CompiledStep`` when the kernels are on and the
parts are the known types — nmpc-rhonn (RhonnModel with its standard or UD EKF, the
default references: BlendedReferences with the bicycle demand, optionally inside the
fused SideslipGuard), nmpc-mf and lmpc (the physics models of model/_substep.py with
LinearReferences) — with one SQP round; otherwise None and the generic step runs.

One step on OSQP's generated solver: ``kernels.step.*_fast_t`` (one call: *_one — inputs,
observe, references, gate, capacity, box, pre-QP, the solver's round, accept/fallback,
allocation, record/prediction — then *_wb), which gets the buffers as one int64 table of
addresses and shapes (``_table``; ``allocate_only`` uses it too). The table holds raw
addresses: this object keeps every array in it alive (``_tab_keep``) and rebuilds it when
one is replaced (a new generated solver after reset(): ``_bind_emb``); the parts' arrays
themselves are never replaced (they are views of fb/db or updated in place). Otherwise
(the Python osqp path) two calls on the same table: ``kernels.step.*_pre_t``, then
``LinearizedMpc.osqp_solve`` (the replaceable OSQP round, Python), then ``*_post_t``
(post and *_wb). The state stays in the parts' own arrays (W, P or U/D, the record, the QP
buffers, the allocator's limits and torques), and their scalar state (counters, flags,
envelopes, last ΔM: the ``Slot`` attributes of core/slots.py) lives in the last
``kernels.step.S_SIZE`` elements of ``fb`` while the step is bound (``bind``, from
MpcController.use_compiled): ``*_wb`` updates it there as the generic step updates the
attributes, so no Python write-back runs, and get_state/set_state, reset, the counters
and ``allocate_only`` read and write the same values through the attributes. The
generic step always runs on unbound state (its own types, e.g. numpy float32 scalars).
Python keeps ControllerOutputs (set from the kernel's result tuple) and the standard
EKF's eigenvalue floor when it may change P (``enforce_spd``, rare). Constants (the
parts' parameter arrays) are copied into packed buffers once here: parameters changed
after the controller was built are not seen by the compiled path (nothing in the package
changes them).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.kernels import step as ks
from controller.core.slots import bind_slots, unbind_slots

_F64 = np.dtype(np.float64)
_ST_FAILED = int(QpStatus.FAILED)
# the io slots, in the order the steps unpack them
assert (ks.IO_VALID, ks.IO_ACTIVE, ks.IO_TT, ks.IO_INVALID, ks.IO_FROZEN, ks.IO_EKF,
        ks.IO_TR, ks.IO_WC, ks.IO_EIG, ks.IO_ERRMS, ks.IO_LEARN, ks.IO_GATE, ks.IO_CONF,
        ks.IO_SINCE, ks.IO_LO, ks.IO_HI, ks.IO_YR, ks.IO_VYR, ks.IO_BR, ks.IO_ENVD,
        ks.IO_DWP, ks.IO_ENVA, ks.IO_NC, ks.IO_ROUNDS, ks.IO_COST, ks.IO_W, ks.IO_GUARD,
        ks.IO_DM, ks.IO_STATUS, ks.IO_FB, ks.IO_TTA, ks.IO_DMA, ks.IO_REC, ks.IO_SIZE) == (
    0, 1, 2, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 20, 21, 22, 23, 24, 25, 26,
    27, 28, 29, 30, 31, 32, 34, 35, 36, 37, 38)


def build_compiled_step(ctrl: Any) -> CompiledStep | None:
    """A CompiledStep for MpcController ``ctrl`` or None (see the module docstring)."""
    from controller.core.learning.ekf import BatchedEkf
    from controller.core.learning.ud_ekf import UdEkf
    from controller.core.model._substep import SubstepModel
    from controller.core.model.rhonn import RhonnModel
    from controller.core.references.intent import BicycleDemand, BlendedReferences
    from controller.core.references.linear import LinearReferences
    from controller.core.references.sideslip_guard import SideslipGuard

    qp, model, al = ctrl.qp, ctrl.model, ctrl.allocator
    if not (qp.kernels and qp._pre_qp is not None and al.kernels and qp.nx == 3):
        return None
    if np.dtype(al.dtype) != np.dtype(qp.dtype):
        return None
    refs = ctrl.references
    if type(model) is RhonnModel:
        if not (model.kernels and ctrl.adaptive and np.dtype(model.dtype) == np.dtype(qp.dtype)
                and type(model.ekf) in (BatchedEkf, UdEkf) and model.ekf.kernels):
            return None
        inner = refs
        if type(refs) is SideslipGuard:
            if not refs.fused:
                return None
            inner = refs.inner
        if not (type(inner) is BlendedReferences and inner._k_prm is not None
                and type(inner.demand) is BicycleDemand):
            return None
        return CompiledStep(ctrl, inner, rhonn=True)
    if isinstance(model, SubstepModel) and type(refs) is LinearReferences:
        if getattr(model, "_kind", -1) < 0 or not model.kernels:
            return None
        return CompiledStep(ctrl, refs, rhonn=False)
    return None


class CompiledStep:
    """The compiled step of one MpcController (see the module docstring)."""

    def __init__(self, ctrl: Any, refs: Any, rhonn: bool) -> None:
        self.ctrl = ctrl
        self.rhonn = rhonn
        # the RHONN re-derives its ΔM gains when Ts changes (RhonnModel._set_split)
        self._split_model = ctrl.model if rhonn else None
        self.refs = refs
        qp, model, al = ctrl.qp, ctrl.model, ctrl.allocator
        self.qp, self.model, self.al = qp, model, al
        dt = qp.dtype
        n = qp.N
        cfg = qp.cfg
        kc = np.zeros(ks.K_SIZE)
        kc[ks.K_PEAK] = ctrl.params.peak_torque_nm
        kc[ks.K_RATIO] = ctrl.params.steering_ratio
        kc[ks.K_VMIN] = ctrl.v_min
        kc[ks.K_CMAX] = cfg.delta_m_max_nm
        vmin_q, us, reg, lim = qp._k_sc
        kc[ks.K_US], kc[ks.K_QVMIN], kc[ks.K_REG], kc[ks.K_LIMIT] = us, vmin_q, reg, lim
        kc[ks.K_RATE] = 1.0 if qp.rate else 0.0
        kc[ks.K_RATE_D] = cfg.rate_limit_nm_per_s * qp.ts / us if qp.rate else 0.0
        kc[ks.K_DECAY] = cfg.fallback_decay
        kc[ks.K_N] = n
        kc[ks.K_F32] = 1.0 if np.dtype(dt) == np.dtype(np.float32) else 0.0
        kc[ks.K_TS] = ctrl.ts
        ci = [np.asarray(qp._k_off, np.intp), qp._tri_r, qp._tri_c]
        db = [al.limits, al.out, al._prm]
        if rhonn:
            kc, s64_n = self._init_rhonn(kc, ci, db)
        else:
            kc, s64_n = self._init_heun(kc)
        # the packed buffers (kernels.step's module docstring); the parts' arrays become
        # views of them, holding the values they had
        kc[ks.K_S64] = ks.FB_KC + len(kc)
        kc[ks.K_YLAST] = ks.FB_KC + len(kc) + s64_n
        self.fb = np.zeros(ks.FB_KC + len(kc) + s64_n + qp.m + ks.S_SIZE)
        self.fb[ks.FB_KC:ks.FB_KC + len(kc)] = kc
        self.io = self.fb[:ks.IO_SIZE]
        self._ylast = self.fb[int(kc[ks.K_YLAST]):self.fb.size - ks.S_SIZE]  # kept y
        self.db = np.zeros(sum(len(a.ravel()) for a in db) + (101 if rhonn else 0), dt)
        self.db[:self.db.size - (101 if rhonn else 0)] = np.concatenate(
            [a.ravel() for a in db])
        self.ci = np.concatenate([np.asarray(a, np.intp).ravel() for a in ci])
        fb, dbv = self.fb, self.db
        o = self.o = ctrl.out
        for obj, attr, buf, at in (
                (ctrl, "_ws", fb, ks.FB_WS), (ctrl, "_x", fb, ks.FB_X),
                (o, "torques", fb, ks.FB_TQ), (o, "model_prediction", fb, ks.FB_PRED),
                (al, "limits", dbv, ks.DB_LIM), (al, "out", dbv, ks.DB_AOUT)):
            old = getattr(obj, attr)
            view = buf[at:at + old.size]
            view[:] = old
            setattr(obj, attr, view)
        if rhonn:
            m = self.model
            for attr, at in (("_rec_phi", ks.DB_RPHI), ("_rec_chi", ks.DB_RCHI)):
                old = getattr(m, attr)
                view = dbv[at:at + old.size]
                view[:] = old
                setattr(m, attr, view)
            ekf = m.ekf
            ea, eb = (ekf.P, np.zeros((3, 15), dt)) if self.std else (ekf.U, ekf.D)
            self._pre_arrays = (fb, m.W, ea, eb, qp._k_buf, qp._k_buf64, dbv, self.ci)
            self._pre, self._post = ks.rhonn_pre_t, ks.rhonn_post_t   # two-call path
            self._one = ks.rhonn_fast_t   # the one call ("step" in the bench's parts)
        else:
            m = self.model
            self._pre_arrays = (fb, m._prm, m._wt, m._wk, qp._k_buf, qp._k_buf64, dbv,
                                self.ci)
            self._pre, self._post = ks.heun_pre_t, ks.heun_post_t     # two-call path
            self._one = ks.heun_fast_t    # the one call ("step" in the bench's parts)
        self._round = qp.osqp_solve   # the OSQP round; another back end may replace it
        self._no_x = np.zeros(n)       # OSQP iterate placeholder when the QP did not run
        # OSQP's generated solver (qp_backend "auto"/"embedded", mpc/osqp_embedded.py): the
        # whole step is one compiled call (kernels.step.*_one) calling its round directly
        self._emb: Any = None
        self.one_call = True          # False: the two-call path also on the generated solver
        self._addr = 0
        self._xs = self._ys = self._no_x
        self._z = np.dtype(dt).type(0.0)   # selects the working dtype of the table's views
        self._tab, self._tab_keep = self._table(self._pre_arrays, self._xs, self._ys, 0)
        if getattr(qp, "_emb", None) is not None:
            self._bind_emb(qp._emb)
        self.warm()

    def __deepcopy__(self, memo: dict) -> CompiledStep:
        # The address table points into this object's buffers: a copy would read and write
        # the original's memory (or freed memory). Copies are refused, not made wrong.
        raise TypeError("a controller with a compiled step cannot be copied or pickled; "
                        "build a new one (registry.make_controller) and set_state() it")

    def __reduce_ex__(self, protocol: Any) -> Any:
        return self.__deepcopy__({})

    # ------------------------------------------------------------------ bound state
    def _slot_map(self) -> list[tuple[Any, list[tuple[str, int]]]]:
        """The parts' Slot attributes (core/slots.py) and their kernels.step S_* slots."""
        out: list[tuple[Any, list[tuple[str, int]]]] = [
            (self.ctrl, [("steps", ks.S_STEPS), ("invalid_steps", ks.S_INV),
                         ("dm_held", ks.S_DMH), ("dm_prev", ks.S_DMP),
                         ("confidence", ks.S_CONF)]),
            (self.al, [("tt_applied", ks.S_TTA), ("dm_applied", ks.S_ADM)]),
            (self.qp, [("_lo_last", ks.S_LO), ("_hi_last", ks.S_HI),
                       ("last_iterations", ks.S_LIT), ("worst_iterations", ks.S_WIT),
                       ("max_iter_hits", ks.S_MIH), ("fallbacks", ks.S_QFB),
                       ("_bounds_dirty", ks.S_DIRTY), ("last_status", ks.S_LST)])]
        if self.rhonn:
            ekf = self.model.ekf
            out += [
                (self.model, [("_has_record", ks.S_REC), ("err_ms", ks.S_ERR),
                              ("learn_steps", ks.S_LEARN), ("_gate_open", ks.S_GATE),
                              ("kt_ts", ks.S_KT), ("kd_now", ks.S_KDN),
                              ("kd_prev", ks.S_KDP)]),
                (ekf.counters, [("updates", ks.S_EUPD), ("rejected", ks.S_EREJ),
                                ("frozen", ks.S_EFRZ), ("trace_resets", ks.S_ETR),
                                ("weight_clips", ks.S_EWC)]),
                (self.refs.demand, [("ay_envelope", ks.S_ENVD), ("_dw_prev", ks.S_DWP)]),
                (self.refs.fixed_point, [("ay_envelope", ks.S_ENVA),
                                         ("rounds_last", ks.S_ROUNDS),
                                         ("cost_last", ks.S_COST),
                                         ("not_converged", ks.S_NC)]),
                (self.refs, [("guard_active_calls", ks.S_GAC), ("weight_last", ks.S_W)])]
            if self.std:
                out.append((ekf, [("_since_eig", ks.S_SINCE)]))
        return out

    def bind(self) -> None:
        """Keep the parts' scalar state in fb's S_* slots (MpcController.use_compiled)."""
        base = self.fb.size - ks.S_SIZE
        for obj, names in self._slot_map():
            bind_slots(obj, self.fb, [(n, base + i) for n, i in names])

    def unbind(self) -> None:
        """Move the scalar state back into the parts' attributes (the generic step keeps
        its own types there, e.g. numpy float32 scalars in float32 mode)."""
        for obj, _ in self._slot_map():
            unbind_slots(obj)

    def _generic(self, inputs: ControllerInputs) -> ControllerOutputs:
        """MpcController.step on unbound state (wheel speeds not a float64 (4,) array)."""
        self.unbind()
        try:
            return type(self.ctrl).step(self.ctrl, inputs)
        finally:
            self.bind()

    def _bind_emb(self, emb: Any) -> None:
        """Use generated solver ``emb`` (LinearizedMpc._emb; a new one after reset())."""
        self._emb = emb
        self._addr = int(emb.round_address())
        self._xs, self._ys = emb.solution.x, emb.solution.y_buf
        self._tab, self._tab_keep = self._table(self._pre_arrays, self._xs, self._ys,
                                                self._addr)

    def _table(self, arrays: tuple, xs: np.ndarray, ys: np.ndarray, solver: int
               ) -> tuple[np.ndarray, tuple]:
        """kernels.step's address table of ``arrays`` (fb, three model arrays, qb, q64,
        db, ci), OSQP's x and y buffers and the solver's round address, and the tuple of
        those arrays that keeps them alive as long as the table is used. Every array must
        be C-contiguous and of the dtype the *_t kernels read it as."""
        fb, a1, a2, a3, qb, q64, db, ci = arrays
        wd = np.dtype(self.qp.dtype)
        model_dt = wd if self.rhonn else _F64
        want = ((fb, _F64), (a1, model_dt), (a2, model_dt), (a3, model_dt), (qb, wd),
                (q64, _F64), (db, wd), (ci, np.dtype(np.intp)), (xs, _F64), (ys, _F64))
        tab = np.zeros(ks.T_SIZE, np.int64)
        for k, (a, dt) in enumerate(want):
            if not a.flags.c_contiguous or a.dtype != dt or a.ndim > ks.T_STRIDE - 1:
                raise ValueError(f"compiled step buffer {k}: {a.dtype} {a.shape} is not a "
                                 f"C-contiguous {dt} array")
            tab[k * ks.T_STRIDE] = a.ctypes.data
            tab[k * ks.T_STRIDE + 1:k * ks.T_STRIDE + 1 + a.ndim] = a.shape
        tab[ks.T_SOLVER] = solver
        return tab, tuple(a for a, _ in want)

    # ------------------------------------------------------------------ set-up
    def _init_rhonn(self, kc: np.ndarray, ci: list, db: list) -> tuple[np.ndarray, int]:
        from controller.core.learning.ekf import BatchedEkf

        m, ekf, refs = self.model, self.model.ekf, self.refs
        fp = refs.fixed_point
        std = type(ekf) is BatchedEkf
        self.std = std
        c = m.cfg
        kc[ks.K_INC] = 1.0 if m.increment else 0.0
        kc[ks.K_FORM] = 0.0 if std else 1.0
        kc[ks.K_EIG] = ekf.cfg.eig_check_every if std else 0.0
        kc[ks.K_GATE_ON] = 1.0 if m._gate_on else 0.0
        kc[ks.K_GATE_A] = m._gate_a
        kc[ks.K_GATE_N] = m._gate_n
        kc[ks.K_GATE_HI] = c.gate_err_hi
        kc[ks.K_GATE_LO] = c.gate_err_lo
        kc[ks.K_EKF:ks.K_EKF + 5] = ekf._sc
        kc[ks.K_HAS_CONF] = 1.0
        kc[ks.K_NUNIT] = len(fp._k_unit)
        kc[ks.K_SPD_MARGIN] = 1e-5 if np.dtype(ekf.dtype) == np.dtype(np.float32) else 1e-9
        assert len(refs._k_prm) == ks.KC_A1 - ks.KC_PRM and len(fp._k_cfg) == 9
        assert len(fp._k_wk) == 4 * len(fp._k_unit)
        ci += [m._d3, m._mono, m._tfac, np.zeros(2, np.intp)]
        db += [m._k_mu, m._k_be, ekf._R, ekf._zeta, m._rec_phi, m._rec_chi]
        kc = np.concatenate((kc, refs._k_prm, fp._k_cfg, fp._k_sm, fp._k_unit))
        assert ekf.L == 15
        return kc, 76 + len(fp._k_wk) + 225

    def _init_heun(self, kc: np.ndarray) -> tuple[np.ndarray, int]:
        from controller.core.model._substep import H_LAMBDA_MAX, MAX_SUBSTEPS, V_LOW_MPS
        from controller.core.references.linear import DEN_MIN, MAX_SPEED_MPS, MAX_STEER_RAD

        m, lin = self.model, self.refs
        self.std = False
        kc[ks.K_KIND] = m._kind
        kc[ks.K_HMAX] = m.h_max
        kc[ks.K_STIFF] = m.stiff_rate
        kc[ks.K_LAMMAX] = H_LAMBDA_MAX
        kc[ks.K_MAXSUB] = MAX_SUBSTEPS
        kc[ks.K_VLOW] = V_LOW_MPS
        kc[ks.K_LIN:ks.K_LIN + 7] = (lin.understeer_gradient, lin.wheelbase_m, lin.p.lr_m,
                                     lin._beta_k, DEN_MIN, MAX_SPEED_MPS, MAX_STEER_RAD)
        return kc, 19

    def warm(self) -> None:
        """Compile (or load from numba's cache) the kernels for these argument types, on
        copies of every array (the controller's state is not touched)."""
        pre = tuple(a.copy() for a in self._pre_arrays)
        xs = np.zeros(self.qp.N)
        ws = np.full(4, 50.0)
        tab, keep = self._table(pre, xs, np.zeros(self.qp.m), 0)   # solver 0: not called
        z = self._z
        ks.alloc_only_t(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, True, True, ws, tab, z)
        one = ks.rhonn_fast_t if self.rhonn else ks.heun_fast_t
        self._pre(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, True, True, 0.0, 0.0, 0.0, ws,
                  tab, z)
        self._post(xs, 0, 0, 0.0, 0.0, tab, z)
        if self._emb is not None:   # sensors invalid: no QP, the solver is not called
            one(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, False, True, 0.0, 0.0, 0.0, ws, tab, z)
        del keep   # the copies outlive every call above

    # ------------------------------------------------------------------ the step
    # A flat body: each Python attribute access or call costs 20–80 ns warm and far more
    # cold (the controller process starts every MPC update with cold caches), so the
    # scalar state stays in fb (bind) and the kernels update it; Python reads the inputs
    # and sets ControllerOutputs from the kernel's tuple (_finish).

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        """One MPC step (MpcController.step's contract); the generic step when the wheel
        speeds are not a float64 (4,) array."""
        ws = inputs.wheel_speeds
        if type(ws) is not np.ndarray or ws.dtype != _F64 or ws.shape != (4,):
            return self._generic(inputs)
        m, o = self._split_model, self.o
        if m is not None and m.ts != m._ts_seen:
            m._set_split()    # Ts·k_tt and the ΔM gains: bound, the kernels read them
        emb = self.qp._emb
        if emb is not None and self.one_call:   # one compiled call, the solver inside
            if emb is not self._emb:
                self._bind_emb(emb)
            return self._finish(self._one(
                float(inputs.swa_rad), float(inputs.accel_pedal), float(inputs.brake_pedal),
                float(inputs.yaw_rate), float(inputs.ax), float(inputs.ay), float(inputs.vx),
                float(inputs.vy), bool(inputs.sensors_valid), bool(inputs.stab_enable),
                o.yaw_rate_ref, o.vy_ref, o.beta_ref, ws, self._tab, self._z), self._ylast)
        # two compiled calls around the OSQP round (the second one ends with *_wb)
        ax, ay = float(inputs.ax), float(inputs.ay)
        run = self._pre(
            float(inputs.swa_rad), float(inputs.accel_pedal), float(inputs.brake_pedal),
            float(inputs.yaw_rate), ax, ay, float(inputs.vx), float(inputs.vy),
            bool(inputs.sensors_valid), bool(inputs.stab_enable), o.yaw_rate_ref, o.vy_ref,
            o.beta_ref, ws, self._tab, self._z)
        y = self._round_py(run)
        return self._finish(self._post(self._xs_py, self._st_py, run, ax, ay, self._tab,
                                       self._z), y)

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        """MpcController.allocate_only on the bound state (kernels.step.alloc_only); the
        generic one when the wheel speeds are not a float64 (4,) array."""
        ws = inputs.wheel_speeds
        if type(ws) is not np.ndarray or ws.dtype != _F64 or ws.shape != (4,):
            self.unbind()
            try:
                return type(self.ctrl).allocate_only(self.ctrl, inputs)
            finally:
                self.bind()
        o = self.o
        o.total_torque, o.delta_m = ks.alloc_only_t(
            float(inputs.swa_rad), float(inputs.accel_pedal), float(inputs.brake_pedal),
            float(inputs.yaw_rate), float(inputs.ax), float(inputs.ay), float(inputs.vx),
            float(inputs.vy), bool(inputs.sensors_valid), bool(inputs.stab_enable), ws,
            self._tab, self._z)
        o.qp_iterations = 0
        return o

    def _finish(self, res: tuple, y: Any) -> ControllerOutputs:
        """ControllerOutputs from a *_wb / *_fast result (the state is already updated in
        fb); ``y``: OSQP's dual iterate, LinearizedMpc._y_last when a solution was
        accepted. Bit 1: spd_clear could not rule out that the standard EKF's eigenvalue
        floor changes P, so it runs here (enforce_spd)."""
        o = self.o
        (ev, o.yaw_rate_ref, o.vy_ref, o.beta_ref, o.total_torque, o.delta_m, o.qp_status,
         o.fallback, o.qp_iterations) = res
        if ev & 1:
            self.qp._y_last = y
        if ev & 2:
            self.model.ekf.enforce_spd()
        return o

    def _round_py(self, run: int) -> Any:
        """The OSQP round through LinearizedMpc.osqp_solve (the Python extension, or the
        generated solver's Python calls) after a pre call that returned ``run`` (bit 0: the
        QP runs; bit 1: its box changed). Leaves the iterate and status for the post call
        in _xs_py/_st_py and the iterations in io; returns OSQP's dual iterate (or None)."""
        if run & 2:
            self.qp._bounds_dirty = True
        self._xs_py, self._st_py, y = self._no_x, _ST_FAILED, None
        iters = 0
        if run & 1:
            iters, st, x, y = self._round()
            self._st_py = int(st)
            if x is not None:
                self._xs_py = x
        self.io[ks.IO_ITERS] = iters
        return y
