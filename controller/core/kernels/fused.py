"""The MPC's whole pre-QP step in one compiled call (reference: ``LinearizedMpc.solve`` in
mpc/qp.py up to the OSQP update: warm start, model rollout + Jacobians, condensing, QP data
and its finiteness check, the float64 copies handed to OSQP).

The same kernels as the step-by-step path (kernels.mpc ``warm_start``, ``condense_build``;
kernels.baselines ``heun_rollout_jac`` or kernels.mpc ``rhonn_rollout_jac``) called from
one compiled function, so the numbers are the same bit for bit; what goes away is the
per-call dispatch and argument unboxing (≈ 55 ns per array argument, measured).

``buf`` is LinearizedMpc's scratch buffer and ``off`` (≥ 15,) the offsets of its views in
the order of ``qp_views``: x̄ (N+1, nx), ū (N,), A (N, nx, nx), B (N, nx),
S (N, nx, N), G (2N, N), ȳ (2N,), y_d (2N,), wdiag (2N,), P (N, N), Px (N(N+1)/2,), q (N,),
sol (N,), b_prev (nx,). Returns True when the QP data are finite and bounded.
"""

from __future__ import annotations

from controller.core.kernels import njit
from controller.core.kernels.baselines import heun_rollout_jac
from controller.core.kernels.mpc import condense_build, rhonn_rollout_jac, warm_start


@njit
def qp_views(buf, off, n, nx):
    """The views of ``buf`` (see the module docstring)."""
    return (buf[off[0]:off[1]].reshape((n + 1, nx)), buf[off[1]:off[2]],
            buf[off[2]:off[3]].reshape((n, nx, nx)), buf[off[3]:off[4]].reshape((n, nx)),
            buf[off[4]:off[5]].reshape((n, nx, n)), buf[off[5]:off[6]].reshape((2 * n, n)),
            buf[off[6]:off[7]], buf[off[7]:off[8]], buf[off[8]:off[9]],
            buf[off[9]:off[10]].reshape((n, n)), buf[off[10]:off[11]], buf[off[11]:off[12]],
            buf[off[12]:off[13]], buf[off[13]:off[14]])


@njit
def _condense_copy(v, n, tri_r, tri_c, px64, q64, has_bp, v_min, us, reg, limit):
    """condense_build on the views ``v`` (qp_views; made once per call, ≈ 0.5 µs) and the
    float64 copies of Px and q for OSQP when the data are usable."""
    Px, q = v[10], v[11]
    ok = condense_build(v[0], v[2], v[3], v[13], has_bp, v_min, us, v[8], reg, v[7], v[1],
                        tri_r, tri_c, v[4], v[5], v[6], v[9], Px, q, limit)
    if ok:
        for k in range(Px.shape[0]):
            px64[k] = Px[k]
        for k in range(n):
            q64[k] = q[k]
    return ok


@njit
def pre_qp_heun(buf, off, n, nx, tri_r, tri_c, px64, q64, x0, dm_min, dm_max, yaw_ref,
                beta_ref, v_min, us, reg, limit, kind, prm, wt, delta, tt, ts, h_max,
                stiff_rate, lam_max, max_sub, vlow, wk):
    """Pre-QP step of a physics baseline (heun_rollout_jac ``kind``; its arguments as
    there); dm_min, dm_max N·m box; yaw_ref rad/s, beta_ref rad; v_min m/s, us N·m per
    decision unit, reg 2λ, limit the QP magnitude bound."""
    v = qp_views(buf, off, n, nx)
    xbar, ubar, A, B = v[0], v[1], v[2], v[3]
    warm_start(v[12], ubar, dm_min, dm_max, v[7], yaw_ref, beta_ref)
    heun_rollout_jac(kind, x0, ubar, prm, wt, delta, tt, ts, h_max, stiff_rate, lam_max,
                     max_sub, vlow, xbar, A, B, wk)
    return _condense_copy(v, n, tri_r, tri_c, px64, q64, False, v_min, us, reg, limit)


@njit
def pre_qp_rhonn(buf, off, n, nx, tri_r, tri_c, px64, q64, x0, dm_min, dm_max, yaw_ref,
                 beta_ref, v_min, us, reg, limit, W, mu, be, kt, kd, kp, u_prev, dw, inc,
                 deriv, phi_ext, dxi, wx):
    """Pre-QP step of the RHONN (rhonn_rollout_jac; its arguments as there). x0 is stored
    in x̄[0] in the buffer's dtype first, as RhonnModel._rollout_kernel does (the kernel
    reads its x0 before it writes x̄[0], so x̄[0] can be passed as x0)."""
    v = qp_views(buf, off, n, nx)
    xbar, ubar, A, B = v[0], v[1], v[2], v[3]
    warm_start(v[12], ubar, dm_min, dm_max, v[7], yaw_ref, beta_ref)
    for c in range(nx):
        xbar[0, c] = x0[c]
    rhonn_rollout_jac(xbar[0], ubar, W, mu, be, kt, kd, kp, u_prev, dw, inc, deriv,
                      phi_ext, dxi, wx, xbar, A, B)
    return _condense_copy(v, n, tri_r, tri_c, px64, q64, True, v_min, us, reg, limit)
