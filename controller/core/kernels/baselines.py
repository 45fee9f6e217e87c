"""Compiled rollout + Jacobians of the linear bicycle (reference: ``BicycleModel`` with
``SubstepModel.predict_linearize`` in model/bicycle.py and model/_substep.py).

Same sub-step count, the same Heun steps of the state and of its sensitivities
S = ∂z/∂x0, sb = ∂z/∂ΔM, the same guards (a non-finite input or result fills the stage
with NaN). Arithmetic in float64; xbar/A/B may be float32 (values rounded on store).
prm (9,): [m kg, Iz kg·m², lf m, lr m, Cf N/rad, Cr N/rad, wB/(2 R Iz) 1/(kg·m), R m,
V_LOW m/s].
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.kernels import njit


@njit
def _bicycle_rhs_jac(vx, vy, r, prm, delta, ax, dm_term, g):
    """g (15,) = (ẋ 3, ∂ẋ/∂x row-major 9, ∂ẋ/∂ΔM 3) of BicycleModel._rhs_jac."""
    m, iz, lf, lr, cf, cr, kdm, vlow = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], \
        prm[6], prm[8]
    d = delta
    if vx > vlow:
        den, dden, steer, dsteer = vx, 1.0, d, 0.0
    elif vx < -vlow:
        den, dden, steer, dsteer = -vx, -1.0, d, 0.0
    else:
        sgn = 1.0 if vx >= 0.0 else -1.0
        den, dden, steer, dsteer = vlow, 0.0, d * sgn * vx / vlow, d * sgn / vlow
    inv = 1.0 / den
    af = (vy + lf * r) * inv - steer
    ar = (vy - lr * r) * inv
    fyf = cf * af
    fyr = cr * ar
    dfyf_vx = -cf * ((vy + lf * r) * inv * inv * dden + dsteer)
    dfyr_vx = -cr * (vy - lr * r) * inv * inv * dden
    g[0] = ax
    g[1] = (fyf + fyr) / m - vx * r
    g[2] = (lf * fyf - lr * fyr) / iz + dm_term
    g[3] = 0.0
    g[4] = 0.0
    g[5] = 0.0
    g[6] = (dfyf_vx + dfyr_vx) / m - r
    g[7] = (cf + cr) * inv / m
    g[8] = (cf * lf - cr * lr) * inv / m - vx
    g[9] = (lf * dfyf_vx - lr * dfyr_vx) / iz
    g[10] = (lf * cf - lr * cr) * inv / iz
    g[11] = (lf * lf * cf + lr * lr * cr) * inv / iz
    g[12] = 0.0
    g[13] = 0.0
    g[14] = kdm


@njit
def bicycle_rollout_jac(x0, ubar, prm, delta, tt, ts, h_max, stiff_rate, lam_max, max_sub,
                        xbar, A, B, wk):
    """x̄ (N+1, 3) from x0 along ū (N,) N·m and the discrete Jacobians A (N, 3, 3), B (N, 3).

    delta: road-wheel angle, rad; tt: total torque, N·m; ts: step, s; h_max s, stiff_rate
    m/s², lam_max, max_sub: the sub-step rule of _substep.py; wk (64,) scratch."""
    n_st = ubar.shape[0]
    ga = wk[0:15]
    gb = wk[15:30]
    S = wk[30:39]
    S1 = wk[39:48]
    JS = wk[48:57]
    for c in range(3):
        xbar[0, c] = x0[c]
    for i in range(n_st):
        z0, z1, z2 = float(xbar[i, 0]), float(xbar[i, 1]), float(xbar[i, 2])
        dm = float(ubar[i])
        ok = (math.isfinite(z0) and math.isfinite(z1) and math.isfinite(z2)
              and math.isfinite(dm) and math.isfinite(delta) and math.isfinite(tt)
              and math.isfinite(ts) and 0.0 < ts <= 1.0)
        n = 0
        if ok:
            vabs = abs(z0)
            lam = stiff_rate / (vabs if vabs > prm[8] else prm[8])
            n = max(math.ceil(ts / h_max - 1e-9), math.ceil(ts * lam / lam_max - 1e-9))
            n = min(max(n, 1), max_sub)
        if n == 0:
            for c in range(3):
                xbar[i + 1, c] = np.nan
                B[i, c] = np.nan
                for d in range(3):
                    A[i, c, d] = np.nan
            continue
        ax = tt / (prm[0] * prm[7])
        dm_term = prm[6] * dm
        h = ts / n
        hh = 0.5 * h
        for k in range(9):
            S[k] = 0.0
        S[0] = 1.0
        S[4] = 1.0
        S[8] = 1.0
        sb0, sb1, sb2 = 0.0, 0.0, 0.0
        for _ in range(n):
            _bicycle_rhs_jac(z0, z1, z2, prm, delta, ax, dm_term, ga)
            for rr in range(3):
                for cc in range(3):
                    JS[3 * rr + cc] = (ga[3 + 3 * rr] * S[cc] + ga[4 + 3 * rr] * S[3 + cc]
                                       + ga[5 + 3 * rr] * S[6 + cc])
            ua0 = ga[3] * sb0 + ga[4] * sb1 + ga[5] * sb2
            ua1 = ga[6] * sb0 + ga[7] * sb1 + ga[8] * sb2
            ua2 = ga[9] * sb0 + ga[10] * sb1 + ga[11] * sb2
            u0, u1, u2 = ua0 + ga[12], ua1 + ga[13], ua2 + ga[14]
            for k in range(9):
                S1[k] = S[k] + h * JS[k]
            _bicycle_rhs_jac(z0 + h * ga[0], z1 + h * ga[1], z2 + h * ga[2], prm, delta, ax,
                             dm_term, gb)
            w0, w1, w2 = sb0 + h * u0, sb1 + h * u1, sb2 + h * u2
            vb0 = gb[3] * w0 + gb[4] * w1 + gb[5] * w2
            vb1 = gb[6] * w0 + gb[7] * w1 + gb[8] * w2
            vb2 = gb[9] * w0 + gb[10] * w1 + gb[11] * w2
            for rr in range(3):
                for cc in range(3):
                    js1 = (gb[3 + 3 * rr] * S1[cc] + gb[4 + 3 * rr] * S1[3 + cc]
                           + gb[5 + 3 * rr] * S1[6 + cc])
                    S[3 * rr + cc] = S[3 * rr + cc] + hh * (JS[3 * rr + cc] + js1)
            sb0 = sb0 + hh * (u0 + vb0 + gb[12])
            sb1 = sb1 + hh * (u1 + vb1 + gb[13])
            sb2 = sb2 + hh * (u2 + vb2 + gb[14])
            z0 += hh * (ga[0] + gb[0])
            z1 += hh * (ga[1] + gb[1])
            z2 += hh * (ga[2] + gb[2])
        tot = z0 + z1 + z2 + sb0 + sb1 + sb2
        for k in range(9):
            tot += S[k]
        if not math.isfinite(tot):
            for c in range(3):
                xbar[i + 1, c] = np.nan
                B[i, c] = np.nan
                for d in range(3):
                    A[i, c, d] = np.nan
            continue
        xbar[i + 1, 0], xbar[i + 1, 1], xbar[i + 1, 2] = z0, z1, z2
        for rr in range(3):
            for cc in range(3):
                A[i, rr, cc] = S[3 * rr + cc]
        B[i, 0], B[i, 1], B[i, 2] = sb0, sb1, sb2
