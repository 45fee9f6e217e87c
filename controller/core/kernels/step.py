"""The MPC step in two compiled calls around the OSQP round (reference:
``MpcController.step`` in mpc/controller.py with the parts it calls; driven by
mpc/compiled.py ``CompiledStep``).

* ``rhonn_pre`` / ``heun_pre``: input finiteness, pedal map, δw, the initial state, the
  EKF observe (RHONN: kernels.ekf ``ekf_observe`` / ``ud_observe``), the references
  (RHONN: kernels.references ``demand_blend`` incl. the sideslip guard; baselines: the
  linear bicycle of references/linear.py), the active gate, ΔM capacity (× the RHONN's
  confidence), the QP box and the pre-QP step (kernels.fused). Returns 0 (no QP this
  step), 1 (run the QP) or 2 (run it; the box l, u changed).
* ``rhonn_post`` / ``heun_post``: accept the OSQP iterate or apply the fallback
  (``LinearizedMpc._finish``), the torque allocation (kernels.allocation ``allocate``)
  and the one-step prediction / record (kernels.mpc ``rhonn_record``, kernels.baselines
  ``heun_rollout_jac``).

The same kernels as the step-by-step path, called in the same order with the same
arguments, so the numbers are the same bit for bit. Scalars that the parts keep as
attributes (counters, envelopes, the gate) come in as arguments and go out through
``io`` (float64, slots IO_*); ``rhonn_wb`` / ``heun_wb`` then apply them to the parts'
bound scalar state (the S_* slots at the end of ``fb``, core/slots.py), and
``rhonn_fast`` / ``heun_fast`` are the one-call step reading that state itself.

Buffers (built once by CompiledStep; the parts' arrays named below are views of them, so
the state stays where the generic step keeps it):
* ``fb`` (float64): io (IO_SIZE,) | the controller's wheel-speed copy (4,) and state x (3,)
  | ControllerOutputs.torques (4,) and .model_prediction (3,) | kc from FB_KC: scalar
  configuration K_* then, for the RHONN, the references' prm (28,), Algorithm 1's cfg (9,),
  sm (4,) and grid (n,) | float64 scratch from kc[K_S64]: [w4 48, coef 12, out 11,
  a1out 5, grid scratch 4n, Cholesky scratch 225] (RHONN) or [ū 1, x̄ 6, A 9, B 3]
  (baselines, the prediction).
* ``db`` (working dtype): the allocator's limits (4,) and torques (4,), its prm (13,);
  RHONN: μ (4,), β (4,), R (3,), ζ (3,), the record φ (15,), χ (3,), then scratch
  [e 3, EKF scratch a 45, b 15, φ 15, φ_ext 17, dxi 3, wx 3].
* ``ci`` (intp): the QP buffer's offsets (18,) | tri_r, tri_c (N(N+1)/2 each) | RHONN:
  deriv (3, 15), mono (15,), tfac (15,), 2 EKF flags (scratch).
* ``qb``: LinearizedMpc's buffer (kernels.fused.qp_views, then lb, ub, z); ``q64``: its
  float64 buffer [Px, q, l, u] handed to OSQP.
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.kernels import AVAILABLE, njit
from controller.core.kernels.allocation import allocate, motor_limits
from controller.core.kernels.baselines import heun_rollout_jac
from controller.core.kernels.ekf import ekf_observe, ud_observe
from controller.core.kernels.fused import pre_qp_heun, pre_qp_rhonn
from controller.core.kernels.mpc import accept_sol, rhonn_record
from controller.core.kernels.references import demand_blend

# --- io slots (float64)
IO_VALID, IO_ACTIVE, IO_TT, IO_DW, IO_DMMIN, IO_DMMAX, IO_INVALID = 0, 1, 2, 3, 4, 5, 6
IO_FROZEN, IO_EKF, IO_TR, IO_WC, IO_EIG, IO_ERRMS, IO_LEARN = 7, 8, 9, 10, 11, 12, 13
IO_GATE, IO_CONF, IO_SINCE, IO_LO, IO_HI, IO_PREOK = 14, 15, 16, 17, 18, 19
IO_YR, IO_VYR, IO_BR = 20, 21, 22
IO_ENVD, IO_DWP, IO_ENVA, IO_NC, IO_ROUNDS, IO_COST, IO_W, IO_GUARD = (
    23, 24, 25, 26, 27, 28, 29, 30)
IO_DM, IO_STATUS, IO_ITERS, IO_FB, IO_TTA, IO_DMA, IO_REC = 31, 32, 33, 34, 35, 36, 37
IO_SIZE = 38

# --- kc scalar slots (float64); model-specific from 14
K_PEAK, K_RATIO, K_VMIN, K_CMAX, K_US, K_QVMIN, K_REG, K_LIMIT = 0, 1, 2, 3, 4, 5, 6, 7
K_RATE, K_RATE_D, K_DECAY, K_N, K_F32, K_TS = 8, 9, 10, 11, 12, 13
K_INC, K_FORM, K_EIG, K_GATE_ON, K_GATE_A, K_GATE_N, K_GATE_HI, K_GATE_LO = (
    14, 15, 16, 17, 18, 19, 20, 21)
K_EKF = 22           # 5 EKF scalars: q, floor, trace_max, p0, w_max
K_HAS_CONF = 27
K_S64, K_NUNIT = 28, 29   # offset of the float64 scratch in fb; grid size (RHONN)
K_YLAST = 30              # offset in fb of the kept dual iterate y (one-call step)
K_SPD_MARGIN = 31         # spd_clear's margin per unit trace (RHONN, standard EKF)
K_KIND, K_HMAX, K_STIFF, K_LAMMAX, K_MAXSUB, K_VLOW = 14, 15, 16, 17, 18, 19
K_LIN = 20           # LinearReferences: K, L, lr, β_k, DEN_MIN, MAX_SPEED, MAX_STEER
K_SIZE = 32
KC_PRM, KC_A1, KC_SM, KC_UNIT = 32, 60, 69, 73

FB_WS, FB_X, FB_TQ, FB_PRED, FB_KC = 38, 42, 45, 49, 52
DB_LIM, DB_AOUT, DB_APRM, DB_MU, DB_BE, DB_R, DB_ZETA, DB_RPHI, DB_RCHI, DB_S = (
    0, 4, 8, 21, 25, 29, 32, 35, 50, 53)
CI_TRI = 18

ST_NOT_RUN, ST_FAILED, ST_MAX_ITER, ST_FALLBACK = 4, 3, 2, 5


@njit
def _pedal(v):
    """pedal_map._pedal: clip to 0..1, non-finite → 0."""
    if not math.isfinite(v):
        return 0.0
    return 0.0 if v < 0.0 else (1.0 if v > 1.0 else v)


@njit
def _inputs(swa, acc, brk, yr, ax, ay, vx, vy, sens, ws, wsc, x, io, kc):
    """Finiteness (controller.inputs_finite), wheel-speed copy, Tt, δw, initial state;
    returns valid. io: VALID, INVALID, TT, DW."""
    s = swa + acc + brk + yr + ax + ay + vx + vy
    t = 0.0
    for i in range(4):
        t += ws[i]
        wsc[i] = ws[i]
    valid = sens and math.isfinite(s + t)
    io[IO_INVALID] = 0.0 if valid else 1.0
    tt = (_pedal(acc) - _pedal(brk)) * 4.0 * kc[K_PEAK]
    dw = swa / kc[K_RATIO] if math.isfinite(swa) else 0.0
    if valid:
        x[0] = vx
        x[1] = vy
        x[2] = yr
        if not math.isfinite(0.0 + x[0] + x[1] + x[2]):
            valid = False
    io[IO_VALID] = 1.0 if valid else 0.0
    io[IO_TT] = tt
    io[IO_DW] = dw
    return valid


@njit
def _capacity(ws, aprm, lim, kc):
    """TorqueAllocator.delta_m_capacity then the cap ``delta_m_max_nm``: (cap N·m, True
    when cap is the dtype's scalar — in float32 mode a numpy float32 in the reference)."""
    motor_limits(ws, aprm, lim)
    two = lim.dtype.type(2.0)
    cap = float(two * min(lim[0] + lim[2], lim[1] + lim[3]))
    is_dt = True
    cmax = kc[K_CMAX]
    if cmax > 0.0 and cmax < cap:    # Python min(cap, cmax) returns cmax only when smaller
        cap = cmax
        is_dt = False
    return cap, is_dt


@njit
def _bounds(cap, is_dt, dm_prev, lo_last, hi_last, qb, qo, q64, io, kc):
    """LinearizedMpc.set_bounds for the box ±cap N·m; True when l, u changed."""
    n = int(kc[K_N])
    us = kc[K_US]
    dm_min, dm_max = -cap, cap
    io[IO_DMMIN] = dm_min
    io[IO_DMMAX] = dm_max
    if kc[K_F32] != 0.0 and is_dt:     # numpy float32 / Python float → float32
        lo = float(np.float32(dm_min) / np.float32(us))
        hi = float(np.float32(dm_max) / np.float32(us))
    else:
        lo, hi = dm_min / us, dm_max / us
    rate = kc[K_RATE] != 0.0
    io[IO_LO] = lo
    io[IO_HI] = hi
    if not rate and lo == lo_last and hi == hi_last:
        return False
    lb = qb[qo[14]:qo[15]]
    ub = qb[qo[15]:qo[16]]
    nt = n * (n + 1) // 2
    m = 2 * n if rate else n
    l_ = q64[nt + n:nt + n + m]
    u_ = q64[nt + n + m:nt + n + 2 * m]
    for i in range(n):
        lb[i] = lo
        ub[i] = hi
        l_[i] = lo
        u_[i] = hi
    if rate:
        d = kc[K_RATE_D]
        p = dm_prev / us if math.isfinite(dm_prev) else 0.0
        l_[n] = p - d
        u_[n] = p + d
        for i in range(n + 1, m):
            l_[i] = -d
            u_[i] = d
    return True


@njit
def spd_clear(P, p_floor, margin, L):
    """True when every P_i (n, m, m) certainly has all eigenvalues above ``p_floor``, so
    that BatchedEkf.enforce_spd would change nothing: a Cholesky factorisation (float64,
    lower triangle as numpy's eigh reads it; scratch L (m·m,)) of P_i − τI succeeds with
    τ = 1.001·p_floor + margin·trace(P_i). The margin is above the rounding of eigh in
    P's dtype, ≈ m·ε·‖P_i‖ ≤ m·ε·trace (float64: 1e-9 vs 3e-15, six orders; float32: 1e-5
    vs 9e-7, ten times), and of the float64 factorisation, so a True here means eigh's
    smallest eigenvalue is ≥ p_floor too. False (also for non-finite entries): run the
    reference enforce_spd (tests/test_compiled_step.py)."""
    n, m = P.shape[0], P.shape[1]
    for f in range(n):
        tr = 0.0
        for j in range(m):
            tr += float(P[f, j, j])
        tau = 1.001 * p_floor + margin * tr
        for j in range(m):
            d = float(P[f, j, j]) - tau
            for k in range(j):
                d -= L[j * m + k] * L[j * m + k]
            if not d > 0.0:
                return False
            d = math.sqrt(d)
            L[j * m + j] = d
            for i in range(j + 1, m):
                t = float(P[f, i, j])
                for k in range(j):
                    t -= L[i * m + k] * L[j * m + k]
                L[i * m + j] = t / d
    return True


@njit
def _run_code(ok, changed):
    """Return code of the pre calls: bit 0 run the QP, bit 1 the box l, u changed."""
    return (1 if ok else 0) + (2 if changed else 0)


@njit
def rhonn_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref, bref,
              has_rec, err_ms, learn_steps, gate_open, since_eig, env_d, dw_prev, env_a,
              lo_last, hi_last, kt_ts, kd_now, kd_prev, ws, fb, W, ea, eb, qb, q64, db, ci):
    """Pre-QP part of the nmpc-rhonn step (module docstring). Arguments: the inputs
    (rad, 0..1, rad/s, m/s², m/s; sens/stab bool), dm_prev N·m, the held references
    (rad/s, m/s, rad), the RHONN's has_record/err_ms (rad/s)²/learn_steps/gate_open, the
    standard EKF's steps since the eigenvalue floor, the references' envelopes m/s² and
    last δw rad, the box last set (decision units), Ts·k_tt (m/s)/(N·m), the ΔM gains
    (rad/s)/(N·m); ws (4,) rad/s; W (3, 15); ea, eb: P and an unused (3, 15) (standard)
    or U, D (UD); fb, db, ci, qb, q64: the buffers (module docstring)."""
    io, wsc, x = fb[0:IO_SIZE], fb[FB_WS:FB_WS + 4], fb[FB_X:FB_X + 3]
    kc = fb[FB_KC:]
    s64 = fb[int(kc[K_S64]):]
    n = int(kc[K_N])
    nt = n * (n + 1) // 2
    qo = ci[0:CI_TRI]
    ct = CI_TRI + 2 * nt
    valid = _inputs(swa, acc, brk, yr, ax, ay, vx, vy, sens, ws, wsc, x, io, kc)
    # --- EKF observe (RhonnModel.observe)
    io[IO_FROZEN] = 0.0
    io[IO_EKF] = -1.0
    io[IO_EIG] = 0.0
    io[IO_TR] = 0.0
    io[IO_WC] = 0.0
    mu, be = db[DB_MU:DB_MU + 4], db[DB_BE:DB_BE + 4]
    R, zeta = db[DB_R:DB_R + 3], db[DB_ZETA:DB_ZETA + 3]
    rec_phi, rec_chi = db[DB_RPHI:DB_RPHI + 15], db[DB_RCHI:DB_RCHI + 3]
    sdt = db[DB_S:]
    e = sdt[0:3]
    flags = ci[ct + 75:ct + 77]
    ke = K_EKF
    if not valid:
        io[IO_FROZEN] = 1.0
    elif has_rec:
        if kc[K_FORM] == 0.0:
            code = ekf_observe(ea, W, rec_phi, x, rec_chi, e, R, zeta, kc[ke], kc[ke + 1],
                               kc[ke + 2], kc[ke + 3], kc[ke + 4], sdt[3:48].reshape((3, 15)),
                               sdt[48:51], flags)
        else:
            code = ud_observe(ea, eb, W, rec_phi, x, rec_chi, e, R, zeta, kc[ke],
                              kc[ke + 1], kc[ke + 2], kc[ke + 3], kc[ke + 4], sdt[3:18],
                              sdt[48:63], flags)
        io[IO_EKF] = code
        if code != 1:
            io[IO_TR] = flags[0]
            io[IO_WC] = flags[1]
            if kc[K_FORM] == 0.0 and kc[K_EIG] > 0.0:
                since_eig += 1
                if since_eig >= kc[K_EIG]:   # the periodic eigenvalue floor: Python's
                    since_eig = 0            # enforce_spd only when it may change P
                    nu = int(kc[K_NUNIT])
                    if not spd_clear(ea, kc[ke + 1], kc[K_SPD_MARGIN],
                                     s64[76 + 4 * nu:76 + 4 * nu + 225]):
                        io[IO_EIG] = 1.0
            er = float(e[2])
            a = kc[K_GATE_A]
            err_ms = a * err_ms + (1.0 - a) * er * er
            learn_steps += 1
    io[IO_SINCE] = since_eig
    io[IO_ERRMS] = err_ms
    io[IO_LEARN] = learn_steps
    # --- references (BlendedReferences._compute_kernel)
    io[IO_ROUNDS] = -1.0
    io[IO_NC] = 0.0
    io[IO_GUARD] = 0.0
    if valid:
        kout = s64[60:71]
        nu = int(kc[K_NUNIT])
        demand_blend(vx, vy, yr, io[IO_DW], ay, env_d, dw_prev, env_a,
                     kc[KC_PRM:KC_PRM + 28], W, ci[ct + 45:ct + 60], ci[ct + 60:ct + 75],
                     s64[0:48].reshape((3, 4, 4)), s64[48:60].reshape((3, 4)),
                     kc[KC_A1:KC_A1 + 9], kc[KC_SM:KC_SM + 4], kc[KC_UNIT:KC_UNIT + nu],
                     s64[76:76 + 4 * nu], s64[71:76], kout)
        if math.isfinite(kout[0] + kout[1] + kout[2]):
            yref, vyref, bref = kout[0], kout[1], kout[2]
        env_d, dw_prev, env_a = kout[3], kout[4], kout[5]
        io[IO_NC] = kout[6]
        io[IO_ROUNDS] = kout[7]
        io[IO_COST] = kout[8]
        io[IO_W] = kout[9]
        io[IO_GUARD] = kout[10]
    io[IO_YR] = yref
    io[IO_VYR] = vyref
    io[IO_BR] = bref
    io[IO_ENVD] = env_d
    io[IO_DWP] = dw_prev
    io[IO_ENVA] = env_a
    # --- active gate, capacity × confidence, box, pre-QP
    active = valid and stab and vx >= kc[K_VMIN]
    io[IO_ACTIVE] = 1.0 if active else 0.0
    io[IO_GATE] = 1.0 if gate_open else 0.0
    io[IO_PREOK] = 0.0
    if not active:
        return 0
    lim = db[DB_LIM:DB_LIM + 4]
    cap, is_dt = _capacity(wsc, db[DB_APRM:DB_APRM + 13], lim, kc)
    if kc[K_HAS_CONF] != 0.0:     # RhonnModel.confidence
        if kc[K_GATE_ON] == 0.0 or gate_open:
            conf = 1.0
        elif learn_steps < kc[K_GATE_N]:
            conf = 0.0
        else:
            hi_e, lo_e = kc[K_GATE_HI], kc[K_GATE_LO]
            rms = math.sqrt(err_ms)
            conf = min(max((hi_e - rms) / (hi_e - lo_e), 0.0), 1.0)
            if conf >= 1.0:
                io[IO_GATE] = 1.0
        io[IO_CONF] = conf
        if kc[K_F32] != 0.0 and is_dt:
            cap = float(np.float32(cap) * np.float32(conf))
        else:
            cap = cap * conf
    changed = _bounds(cap, is_dt, dm_prev, lo_last, hi_last, qb, qo, q64, io, kc)
    # the dead-time column b_prev = [0, 0, kd_prev] (LinearizedMpc._k_bp)
    bp = qb[qo[13]:qo[14]]
    bp[0] = 0.0
    bp[1] = 0.0
    bp[2] = kd_prev
    ok = pre_qp_rhonn(qb, qo, n, 3, ci[CI_TRI:CI_TRI + nt], ci[CI_TRI + nt:ct], q64[0:nt],
                      q64[nt:nt + n], x, -cap, cap, yref, bref, kc[K_QVMIN], kc[K_US],
                      kc[K_REG], kc[K_LIMIT], W, mu, be, kt_ts * io[IO_TT], kd_now, kd_prev,
                      dm_prev, io[IO_DW], kc[K_INC] != 0.0, ci[ct:ct + 45].reshape((3, 15)),
                      sdt[78:95], sdt[95:98], sdt[98:101])
    io[IO_PREOK] = 1.0 if ok else 0.0
    return _run_code(ok, changed)


@njit
def heun_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref, bref,
             lo_last, hi_last, ws, fb, prm, wt, wk, qb, q64, db, ci):
    """Pre-QP part of the nmpc-mf / lmpc step (module docstring; arguments as rhonn_pre,
    prm/wt/wk the physics model's parameter vector, wheel table and scratch)."""
    io, wsc, x = fb[0:IO_SIZE], fb[FB_WS:FB_WS + 4], fb[FB_X:FB_X + 3]
    kc = fb[FB_KC:]
    n = int(kc[K_N])
    nt = n * (n + 1) // 2
    qo = ci[0:CI_TRI]
    valid = _inputs(swa, acc, brk, yr, ax, ay, vx, vy, sens, ws, wsc, x, io, kc)
    dw = io[IO_DW]
    if valid:     # LinearReferences.compute
        kl = K_LIN
        if not (abs(vx) <= kc[kl + 5] and abs(dw) <= kc[kl + 6]):
            r_d, vy_d, b_d = 0.0, 0.0, 0.0
        else:
            v2 = vx * vx
            den = 1.0 + kc[kl] * v2
            if den < kc[kl + 4]:
                den = kc[kl + 4]
            L = kc[kl + 1]
            r_d = vx * dw / (L * den)
            b_d = dw * (kc[kl + 2] - kc[kl + 3] * v2) / (L * den)
            vy_d = b_d * vx
        if math.isfinite(r_d + vy_d + b_d):
            yref, vyref, bref = r_d, vy_d, b_d
    io[IO_YR] = yref
    io[IO_VYR] = vyref
    io[IO_BR] = bref
    active = valid and stab and vx >= kc[K_VMIN]
    io[IO_ACTIVE] = 1.0 if active else 0.0
    io[IO_PREOK] = 0.0
    if not active:
        return 0
    cap, is_dt = _capacity(wsc, db[DB_APRM:DB_APRM + 13], db[DB_LIM:DB_LIM + 4], kc)
    changed = _bounds(cap, is_dt, dm_prev, lo_last, hi_last, qb, qo, q64, io, kc)
    ok = pre_qp_heun(qb, qo, n, 3, ci[CI_TRI:CI_TRI + nt], ci[CI_TRI + nt:CI_TRI + 2 * nt],
                     q64[0:nt], q64[nt:nt + n], x, -cap, cap, yref, bref, kc[K_QVMIN],
                     kc[K_US], kc[K_REG], kc[K_LIMIT], int(kc[K_KIND]), prm, wt, dw,
                     io[IO_TT], kc[K_TS], kc[K_HMAX], kc[K_STIFF], kc[K_LAMMAX],
                     int(kc[K_MAXSUB]), kc[K_VLOW], wk)
    io[IO_PREOK] = 1.0 if ok else 0.0
    return _run_code(ok, changed)


@njit
def _accept_alloc(xs, status, dm_prev, ax, ay, fb, qb, db, ci):
    """LinearizedMpc accept/_finish (or ΔM = 0 when not active), then the allocation
    (MpcController._allocate). status: OSQP's mapped status (QpStatus value, FAILED when
    it failed or did not run). io: DM, STATUS, FB, TTA, DMA."""
    io, wsc, kc = fb[0:IO_SIZE], fb[FB_WS:FB_WS + 4], fb[FB_KC:]
    qo = ci[0:CI_TRI]
    active = io[IO_ACTIVE] != 0.0
    sol = qb[qo[12]:qo[13]]
    n = sol.shape[0]
    fb_ = False
    dm = 0.0
    if active:
        ok = False
        if io[IO_PREOK] != 0.0 and status != ST_FAILED:
            ubar = qb[qo[1]:qo[2]]
            ok = accept_sol(xs, qb[qo[14]:qo[15]], qb[qo[15]:qo[16]], kc[K_US],
                            qb[qo[16]:qo[17]], ubar, sol)
            if ok:
                dm = float(ubar[0])
            else:
                status = ST_FAILED
        if not ok:   # the defined fallback
            dm = kc[K_DECAY] * (dm_prev if math.isfinite(dm_prev) else 0.0)
            dm = min(max(dm, io[IO_DMMIN]), io[IO_DMMAX])
            for i in range(n):
                sol[i] = dm
            status = ST_FALLBACK
            fb_ = True
    else:
        status = ST_NOT_RUN
        for i in range(n):
            sol[i] = 0.0
    io[IO_DM] = dm
    io[IO_STATUS] = status
    io[IO_FB] = 1.0 if fb_ else 0.0
    aout = db[DB_AOUT:DB_AOUT + 4]
    tta, dma = allocate(io[IO_TT], dm, ax, ay, wsc, db[DB_LIM:DB_LIM + 4], active,
                        db[DB_APRM:DB_APRM + 13], aout)
    for i in range(4):
        fb[FB_TQ + i] = aout[i]
    io[IO_TTA] = tta
    io[IO_DMA] = dma
    return float(tta), float(dma)


@njit
def rhonn_post(xs, status, dm_prev, ax, ay, kt_ts, kd_now, kd_prev, fb, W, qb, db, ci):
    """Post-QP part of the nmpc-rhonn step: accept/fallback, allocation, record
    (RhonnModel.record). xs: OSQP's iterate (decision units); status as _accept_alloc."""
    tta, dma = _accept_alloc(xs, status, dm_prev, ax, ay, fb, qb, db, ci)
    io, x, pred, kc = fb[0:IO_SIZE], fb[FB_X:FB_X + 3], fb[FB_PRED:FB_PRED + 3], fb[FB_KC:]
    rec = False
    if io[IO_VALID] != 0.0:
        sdt = db[DB_S:]
        rec = rhonn_record(float(x[0]), float(x[1]), float(x[2]), W, db[DB_MU:DB_MU + 4],
                           db[DB_BE:DB_BE + 4], io[IO_DW], kt_ts * tta,
                           kd_now * dma + kd_prev * dm_prev, kc[K_INC] != 0.0, sdt[63:78],
                           sdt[98:101], pred, db[DB_RPHI:DB_RPHI + 15],
                           db[DB_RCHI:DB_RCHI + 3])
    else:
        for i in range(3):
            pred[i] = np.nan
    io[IO_REC] = 1.0 if rec else 0.0


@njit
def heun_post(xs, status, dm_prev, ax, ay, fb, prm, wt, wk, qb, db, ci):
    """Post-QP part of the nmpc-mf / lmpc step: accept/fallback, allocation, one-step
    prediction (the physics model's predict: one compiled stage in float64)."""
    tta, dma = _accept_alloc(xs, status, dm_prev, ax, ay, fb, qb, db, ci)
    io, x, pred, kc = fb[0:IO_SIZE], fb[FB_X:FB_X + 3], fb[FB_PRED:FB_PRED + 3], fb[FB_KC:]
    if io[IO_VALID] != 0.0:
        s64 = fb[int(kc[K_S64]):]
        u1 = s64[0:1]
        xb = s64[1:7].reshape((2, 3))
        u1[0] = dma
        heun_rollout_jac(int(kc[K_KIND]), x, u1, prm, wt, io[IO_DW], tta, kc[K_TS],
                         kc[K_HMAX], kc[K_STIFF], kc[K_LAMMAX], int(kc[K_MAXSUB]),
                         kc[K_VLOW], xb, s64[7:16].reshape((1, 3, 3)),
                         s64[16:19].reshape((1, 3)), wk)
        for i in range(3):
            pred[i] = xb[1, i]
    else:
        for i in range(3):
            pred[i] = np.nan


# ---------------------------------------------------------------------- one call
# With OSQP's generated solver (mpc/osqp_embedded.py) the QP round is a C function
# ``long long rh_round(int flags)`` on buffers bound at set-up; the step then is one
# compiled call: pre → rh_round → post. Its address is an int64 argument (a numba
# first-class function object as an argument costs ≈ 10 µs of dispatch, measured).

if AVAILABLE:
    from llvmlite import ir as _ir
    from numba import types as _types
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def call_round(typingctx, addr, flags):
        """Call ``long long f(int)`` at ``addr`` (int64) with ``flags`` (int32)."""
        sig = _types.int64(_types.int64, _types.int32)

        def codegen(context, builder, signature, args):
            fnty = _ir.FunctionType(_ir.IntType(64), [_ir.IntType(32)])
            fn = builder.inttoptr(args[0], fnty.as_pointer())
            return builder.call(fn, [args[1]])

        return sig, codegen

    @_intrinsic
    def at_address(typingctx, addr, proto):
        """Pointer to ``proto``'s type (a float or int scalar) at integer ``addr``; with
        ``numba.carray`` the array over memory a caller keeps alive, without a meminfo."""
        if not isinstance(addr, _types.Integer) or not isinstance(
                proto, (_types.Float, _types.Integer)):
            return None
        rt = _types.CPointer(proto)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(rt))

        return rt(addr, proto), codegen

    from numba import carray as _carray
else:  # pragma: no cover - without numba no compiled step is built
    def call_round(addr, flags):
        raise RuntimeError("needs numba")

    def at_address(addr, proto):
        raise RuntimeError("needs numba")

    _carray = None


@njit
def _embedded_round(run, addr, dirty, io):
    """The OSQP round on the generated solver when ``run`` asks for it: flags bit 0 = the
    box changed now or before (LinearizedMpc._bounds_dirty); returns the mapped status
    (QpStatus value; FAILED when not run) and writes the iterations to io[ITERS]."""
    io[IO_ITERS] = 0.0
    if not run & 1:
        return ST_FAILED
    fl = 1 if (run & 2 or dirty) else 0
    r = call_round(np.int64(addr), np.int32(fl))
    it = r // 64                       # STATUS_SHIFT of mpc/osqp_embedded.py
    sv = r - it * 64
    io[IO_ITERS] = it
    if sv == 1:
        return 0                       # SOLVED
    if sv == 2:
        return 1                       # SOLVED_INACCURATE
    if sv == 7 or sv == 8:
        return ST_MAX_ITER
    return ST_FAILED


@njit
def _keep_y(fb, y):
    """fb's kept y ← OSQP's dual iterate when the step accepted a solution
    (LinearizedMpc._y_last)."""
    io = fb[0:IO_SIZE]
    if io[IO_ACTIVE] != 0.0 and io[IO_FB] == 0.0:
        k = int(fb[FB_KC + K_YLAST])
        for i in range(y.shape[0]):
            fb[k + i] = y[i]


@njit
def rhonn_one(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref, bref,
              has_rec, err_ms, learn_steps, gate_open, since_eig, env_d, dw_prev, env_a,
              lo_last, hi_last, kt_ts, kd_now, kd_prev, ws, fb, W, ea, eb, qb, q64, db, ci,
              addr, dirty, xs, y):
    """The whole nmpc-rhonn step: rhonn_pre, the generated solver's round at ``addr``
    (``dirty``: LinearizedMpc._bounds_dirty; xs, y: its bound x and y buffers),
    rhonn_post. Returns rhonn_pre's code."""
    run = rhonn_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref,
                    bref, has_rec, err_ms, learn_steps, gate_open, since_eig, env_d, dw_prev,
                    env_a, lo_last, hi_last, kt_ts, kd_now, kd_prev, ws, fb, W, ea, eb, qb,
                    q64, db, ci)
    status = _embedded_round(run, addr, dirty, fb)
    rhonn_post(xs, status, dm_prev, ax, ay, kt_ts, kd_now, kd_prev, fb, W, qb, db, ci)
    _keep_y(fb, y)
    return run


@njit
def heun_one(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref, bref,
             lo_last, hi_last, ws, fb, prm, wt, wk, qb, q64, db, ci, addr, dirty, xs, y):
    """The whole nmpc-mf / lmpc step in one call (as rhonn_one)."""
    run = heun_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, dm_prev, yref, vyref,
                   bref, lo_last, hi_last, ws, fb, prm, wt, wk, qb, q64, db, ci)
    status = _embedded_round(run, addr, dirty, fb)
    heun_post(xs, status, dm_prev, ax, ay, fb, prm, wt, wk, qb, db, ci)
    _keep_y(fb, y)
    return run


# --- the parts' scalar state (core/slots.py Slot attributes), the last S_SIZE elements of
# fb: CompiledStep binds MpcController, TorqueAllocator, LinearizedMpc and (RHONN) the
# model, the demand, Algorithm 1 and the blended references to them, and the *_fast
# kernels below read them and apply the updates CompiledStep used to write back.
S_STEPS, S_INV, S_DMH, S_DMP, S_CONF, S_TTA, S_ADM = 0, 1, 2, 3, 4, 5, 6
S_LO, S_HI, S_LIT, S_WIT, S_MIH, S_QFB, S_DIRTY, S_LST = 7, 8, 9, 10, 11, 12, 13, 14
S_REC, S_ERR, S_LEARN, S_GATE = 15, 16, 17, 18
S_ENVD, S_DWP, S_ENVA, S_ROUNDS, S_COST, S_NC, S_GAC, S_W = 19, 20, 21, 22, 23, 24, 25, 26
# RHONN: the standard EKF's steps since the eigenvalue floor, the model's Ts·k_tt and ΔM
# gains, the EKF's counters (updates, rejected, frozen, trace resets, weight clips)
S_SINCE, S_KT, S_KDN, S_KDP = 27, 28, 29, 30
S_EUPD, S_EREJ, S_EFRZ, S_ETR, S_EWC = 31, 32, 33, 34, 35
S_SIZE = 36


@njit
def _state_common(fb, st, run, dirty, set_dirty):
    """What the step sets on MpcController (steps, invalid_steps, dm_held, dm_prev),
    TorqueAllocator (tt/dm_applied) and LinearizedMpc (set_bounds, _finish; with
    ``set_dirty`` also _bounds_dirty after the generated solver's round, which ran with
    ``dirty``) after one step: returns (active, status, fallback, iterations, y accepted)."""
    io = fb[0:IO_SIZE]
    if set_dirty:
        st[S_DIRTY] = 0.0 if run & 1 else (1.0 if (dirty or run & 2 != 0) else 0.0)
    st[S_STEPS] += 1.0
    if io[IO_INVALID] != 0.0:
        st[S_INV] += 1.0
    dma = io[IO_DMA]
    st[S_DMH] = io[IO_DM]
    st[S_DMP] = dma
    st[S_TTA] = io[IO_TTA]
    st[S_ADM] = dma
    status = int(io[IO_STATUS])
    fbk = io[IO_FB] != 0.0
    iters = int(io[IO_ITERS])
    active = io[IO_ACTIVE] != 0.0
    accepted = False
    if active:
        st[S_LO] = io[IO_LO]
        st[S_HI] = io[IO_HI]
        st[S_LIT] = iters
        if iters > st[S_WIT]:
            st[S_WIT] = iters
        if status == ST_MAX_ITER:
            st[S_MIH] += 1.0
        if fbk:
            st[S_QFB] += 1.0
        else:
            accepted = True
        st[S_LST] = status
    else:
        iters = 0
    return active, status, fbk, iters, accepted


@njit
def rhonn_wb(fb, run, dirty, set_dirty):
    """The bound state's update after one nmpc-rhonn step (what CompiledStep wrote back
    before): returns (events, yaw-rate ref, vy ref, β ref, Tt, ΔM applied, QP status,
    fallback, QP iterations) for ControllerOutputs; events bit 0: y accepted
    (LinearizedMpc._y_last), bit 1: the standard EKF's eigenvalue floor must run in Python
    (spd_clear could not rule out that it changes P: BatchedEkf.enforce_spd)."""
    st = fb[fb.shape[0] - S_SIZE:]
    active, status, fbk, iters, accepted = _state_common(fb, st, run, dirty, set_dirty)
    io = fb[0:IO_SIZE]
    if active:
        st[S_CONF] = io[IO_CONF]
        if io[IO_GATE] != 0.0:
            st[S_GATE] = 1.0
    st[S_REC] = 1.0 if io[IO_REC] != 0.0 else 0.0
    code = io[IO_EKF]
    ev = 1 if accepted else 0
    if code >= 0.0:             # EkfCounters: rejected, or accepted (with guard flags)
        if code == 1.0:
            st[S_EREJ] += 1.0
        else:
            st[S_ERR] = io[IO_ERRMS]
            st[S_LEARN] = float(int(io[IO_LEARN]))
            st[S_EUPD] += 1.0
            if code == 2.0:
                st[S_ETR] += float(int(io[IO_TR]))
                st[S_EWC] += float(int(io[IO_WC]))
            st[S_SINCE] = float(int(io[IO_SINCE]))
            if io[IO_EIG] != 0.0:
                ev += 2
    elif io[IO_FROZEN] != 0.0:
        st[S_EFRZ] += 1.0
    if io[IO_VALID] != 0.0:
        st[S_ENVD] = io[IO_ENVD]
        st[S_DWP] = io[IO_DWP]
        st[S_ENVA] = io[IO_ENVA]
        if io[IO_GUARD] != 0.0:
            st[S_GAC] += 1.0
        if io[IO_ROUNDS] >= 0.0:
            st[S_ROUNDS] = float(int(io[IO_ROUNDS]))
            st[S_COST] = io[IO_COST]
        if io[IO_NC] != 0.0:
            st[S_NC] += 1.0
        st[S_W] = io[IO_W]
    return (ev, io[IO_YR], io[IO_VYR], io[IO_BR], io[IO_TT], io[IO_DMA], status, fbk, iters)


@njit
def heun_wb(fb, run, dirty, set_dirty):
    """The bound state's update after one nmpc-mf / lmpc step (as rhonn_wb; events
    bit 0 only)."""
    st = fb[fb.shape[0] - S_SIZE:]
    _, status, fbk, iters, accepted = _state_common(fb, st, run, dirty, set_dirty)
    io = fb[0:IO_SIZE]
    return (1 if accepted else 0, io[IO_YR], io[IO_VYR], io[IO_BR], io[IO_TT], io[IO_DMA],
            status, fbk, iters)


@njit
def rhonn_fast(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, fb, W,
               ea, eb, qb, q64, db, ci, addr, xs, y):
    """rhonn_one with the bound scalar state read from fb (S_*), then rhonn_wb."""
    st = fb[fb.shape[0] - S_SIZE:]
    dirty = st[S_DIRTY] != 0.0
    run = rhonn_one(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, st[S_DMP], yref, vyref,
                    bref, st[S_REC] != 0.0, st[S_ERR], int(st[S_LEARN]), st[S_GATE] != 0.0,
                    int(st[S_SINCE]), st[S_ENVD], st[S_DWP], st[S_ENVA], st[S_LO], st[S_HI],
                    st[S_KT], st[S_KDN], st[S_KDP], ws, fb, W, ea, eb, qb, q64, db, ci, addr,
                    dirty, xs, y)
    return rhonn_wb(fb, run, dirty, True)


@njit
def heun_fast(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, fb,
              prm, wt, wk, qb, q64, db, ci, addr, xs, y):
    """heun_one with the bound scalar state read from fb (S_*), then heun_wb."""
    st = fb[fb.shape[0] - S_SIZE:]
    dirty = st[S_DIRTY] != 0.0
    run = heun_one(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, st[S_DMP], yref, vyref,
                   bref, st[S_LO], st[S_HI], ws, fb, prm, wt, wk, qb, q64, db, ci, addr,
                   dirty, xs, y)
    return heun_wb(fb, run, dirty, True)


@njit
def alloc_only(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, ws, fb, db):
    """MpcController.allocate_only on the bound state: re-allocate the held ΔM (S_DMH)
    with the pedal torque; the wheel-speed copy, ControllerOutputs.torques and the
    allocator's torques in place, S_TTA/S_ADM/S_DMP updated. Returns (Tt, ΔM applied)."""
    kc = fb[FB_KC:]
    st = fb[fb.shape[0] - S_SIZE:]
    wsc = fb[FB_WS:FB_WS + 4]
    s = swa + acc + brk + yr + ax + ay + vx + vy
    t = 0.0
    for i in range(4):
        t += ws[i]
        wsc[i] = ws[i]
    ok = math.isfinite(s + t) and sens and stab and vx >= kc[K_VMIN]
    tt = (_pedal(acc) - _pedal(brk)) * 4.0 * kc[K_PEAK]
    dm = st[S_DMH] if ok else 0.0
    aout = db[DB_AOUT:DB_AOUT + 4]
    tta, dma = allocate(tt, dm, ax, ay, wsc, db[DB_LIM:DB_LIM + 4], False,
                        db[DB_APRM:DB_APRM + 13], aout)
    for i in range(4):
        fb[FB_TQ + i] = aout[i]
    st[S_TTA] = float(tta)
    st[S_ADM] = float(dma)
    st[S_DMP] = float(dma)
    return tt, float(dma)


@njit
def rhonn_pre_b(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, fb, W,
                ea, eb, qb, q64, db, ci):
    """rhonn_pre with the bound scalar state read from fb (S_*; two-call path)."""
    st = fb[fb.shape[0] - S_SIZE:]
    return rhonn_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, st[S_DMP], yref, vyref,
                     bref, st[S_REC] != 0.0, st[S_ERR], int(st[S_LEARN]), st[S_GATE] != 0.0,
                     int(st[S_SINCE]), st[S_ENVD], st[S_DWP], st[S_ENVA], st[S_LO],
                     st[S_HI], st[S_KT], st[S_KDN], st[S_KDP], ws, fb, W, ea, eb, qb, q64,
                     db, ci)


@njit
def rhonn_post_wb(xs, status, run, ax, ay, fb, W, qb, db, ci):
    """rhonn_post (ΔM of the last step from S_DMP), then rhonn_wb (two-call path; the
    OSQP round keeps LinearizedMpc._bounds_dirty itself)."""
    st = fb[fb.shape[0] - S_SIZE:]
    rhonn_post(xs, status, st[S_DMP], ax, ay, st[S_KT], st[S_KDN], st[S_KDP], fb, W, qb, db,
               ci)
    return rhonn_wb(fb, run, False, False)


@njit
def heun_pre_b(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, fb,
               prm, wt, wk, qb, q64, db, ci):
    """heun_pre with the bound scalar state read from fb (S_*; two-call path)."""
    st = fb[fb.shape[0] - S_SIZE:]
    return heun_pre(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, st[S_DMP], yref, vyref,
                    bref, st[S_LO], st[S_HI], ws, fb, prm, wt, wk, qb, q64, db, ci)


@njit
def heun_post_wb(xs, status, run, ax, ay, fb, prm, wt, wk, qb, db, ci):
    """heun_post (ΔM of the last step from S_DMP), then heun_wb (two-call path)."""
    st = fb[fb.shape[0] - S_SIZE:]
    heun_post(xs, status, st[S_DMP], ax, ay, fb, prm, wt, wk, qb, db, ci)
    return heun_wb(fb, run, False, False)


# ---------------------------------------------------------------------- address table
# The one-call entries take the step's buffers as one int64 table — per buffer its
# address and shape (T_STRIDE slots), then the generated solver's round address — built by
# CompiledStep (mpc/compiled.py), which keeps every buffer in it alive. Inside, the arrays
# are numba.carray views without a meminfo: passing ten arrays from Python cost ten
# unboxings (each a meminfo allocated and freed) and every slice and call inside the step
# an atomic reference count (NRT_incref/decref: ≈ 540 call sites in rhonn_pre alone);
# measured, nmpc-rhonn step p50 11.1–11.4 → 8.2–8.6 µs, the same numbers bit for bit.
T_FB, T_A1, T_A2, T_A3, T_QB, T_Q64, T_DB, T_CI, T_XS, T_Y = (
    0, 4, 8, 12, 16, 20, 24, 28, 32, 36)
T_STRIDE = 4
T_SOLVER = 40
T_SIZE = 41


@njit
def _v1(t, k, proto):
    """The 1-d buffer at table entry ``k`` (elements of ``proto``'s type)."""
    return _carray(at_address(t[k], proto), t[k + 1])


@njit
def _v2(t, k, proto):
    """The 2-d buffer at table entry ``k``."""
    return _carray(at_address(t[k], proto), (t[k + 1], t[k + 2]))


@njit
def _v3(t, k, proto):
    """The 3-d buffer at table entry ``k``."""
    return _carray(at_address(t[k], proto), (t[k + 1], t[k + 2], t[k + 3]))


@njit
def _rhonn_bufs(t, z):
    """The RHONN step's buffers of table ``t``: fb, W, P or U, the unused (3, 15) or D, qb,
    q64, db, ci; ``z``: a zero of the working dtype."""
    i0 = t[T_CI] - t[T_CI]             # an intp zero: ci's element type
    return (_v1(t, T_FB, 0.0), _v2(t, T_A1, z), _v3(t, T_A2, z), _v2(t, T_A3, z),
            _v1(t, T_QB, z), _v1(t, T_Q64, 0.0), _v1(t, T_DB, z), _v1(t, T_CI, i0))


@njit
def _heun_bufs(t, z):
    """The physics baselines' buffers of table ``t``: fb, prm, wt, wk, qb, q64, db, ci."""
    i0 = t[T_CI] - t[T_CI]
    return (_v1(t, T_FB, 0.0), _v1(t, T_A1, 0.0), _v2(t, T_A2, 0.0), _v1(t, T_A3, 0.0),
            _v1(t, T_QB, z), _v1(t, T_Q64, 0.0), _v1(t, T_DB, z), _v1(t, T_CI, i0))


@njit
def rhonn_fast_t(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, t,
                 z):
    """rhonn_fast on the buffers of table ``t`` and its solver, x and y."""
    fb, W, ea, eb, qb, q64, db, ci = _rhonn_bufs(t, z)
    return rhonn_fast(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws,
                      fb, W, ea, eb, qb, q64, db, ci, t[T_SOLVER], _v1(t, T_XS, 0.0),
                      _v1(t, T_Y, 0.0))


@njit
def heun_fast_t(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, t, z):
    """heun_fast on the buffers of table ``t`` and its solver, x and y."""
    fb, prm, wt, wk, qb, q64, db, ci = _heun_bufs(t, z)
    return heun_fast(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws,
                     fb, prm, wt, wk, qb, q64, db, ci, t[T_SOLVER], _v1(t, T_XS, 0.0),
                     _v1(t, T_Y, 0.0))


@njit
def alloc_only_t(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, ws, t, z):
    """alloc_only on fb and db of table ``t``."""
    return alloc_only(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, ws, _v1(t, T_FB, 0.0),
                      _v1(t, T_DB, z))


@njit
def rhonn_pre_t(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, t, z):
    """rhonn_pre_b on the buffers of table ``t`` (two-call path)."""
    fb, W, ea, eb, qb, q64, db, ci = _rhonn_bufs(t, z)
    return rhonn_pre_b(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws,
                       fb, W, ea, eb, qb, q64, db, ci)


@njit
def rhonn_post_t(xs, status, run, ax, ay, t, z):
    """rhonn_post_wb on the buffers of table ``t``; ``xs``: the OSQP round's iterate."""
    fb, W, _, _, qb, _, db, ci = _rhonn_bufs(t, z)
    return rhonn_post_wb(xs, status, run, ax, ay, fb, W, qb, db, ci)


@njit
def heun_pre_t(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws, t, z):
    """heun_pre_b on the buffers of table ``t`` (two-call path)."""
    fb, prm, wt, wk, qb, q64, db, ci = _heun_bufs(t, z)
    return heun_pre_b(swa, acc, brk, yr, ax, ay, vx, vy, sens, stab, yref, vyref, bref, ws,
                      fb, prm, wt, wk, qb, q64, db, ci)


@njit
def heun_post_t(xs, status, run, ax, ay, t, z):
    """heun_post_wb on the buffers of table ``t``; ``xs``: the OSQP round's iterate."""
    fb, prm, wt, wk, qb, _, db, ci = _heun_bufs(t, z)
    return heun_post_wb(xs, status, run, ax, ay, fb, prm, wt, wk, qb, db, ci)
