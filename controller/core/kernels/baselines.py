"""Compiled rollout + Jacobians of the physics baselines (references: ``BicycleModel`` and
``SevenDofPrediction`` with ``SubstepModel.predict_linearize`` in model/bicycle.py,
model/seven_dof.py and model/_substep.py).

Same sub-step count, the same Heun steps of the state and of its sensitivities
S = ∂z/∂x0, sb = ∂z/∂ΔM, the same guards (a non-finite input or result fills the stage
with NaN). Arithmetic in float64; xbar/A/B may be float32 (values rounded on store).

Bicycle (kind 0) prm (9,): [m kg, Iz kg·m², lf m, lr m, Cf N/rad, Cr N/rad,
wB/(2 R Iz) 1/(kg·m), R m, V_LOW m/s].
7-DoF (kind 1, quasi-steady slip) prm (10,): [m kg, Iz kg·m², R m, μ_nominal -,
rolling f·g m/s², rolling ramp speed m/s, drag k/m 1/m, MF tyres (1) or linear (0),
V_LOW m/s, FZ_MIN N]; wheel table wt (4, 18) per wheel FL, FR, RL, RR: [x m, y m,
front (0/1), Fz_static N, kx_ax, ky_ay N/(m/s²), c_lin N/rad, side ±1, Fz cap N,
MF lateral curve fz0, c, d1, d2, k1, k2, k3, e1, e2] (see tyre.py ``MfCurve``).
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
def _mf_eval(wt, i, s, fz_n, mu, out):
    """out[0:3] = (F N, ∂F/∂s, ∂F/∂Fz) of the lateral MF curve of wheel i (tyre.mf_eval)."""
    fz0 = wt[i, 9]
    c, d1, d2, k1, k2, k3, e1, e2 = (wt[i, 10], wt[i, 11], wt[i, 12], wt[i, 13], wt[i, 14],
                                     wt[i, 15], wt[i, 16], wt[i, 17])
    dfz = (fz_n - fz0) / fz0
    ex = math.exp(k3 * dfz)
    kpoly = k1 + k2 * dfz
    K = fz_n * kpoly * ex
    dK = ex * (kpoly + fz_n * (k2 + kpoly * k3) / fz0)
    dpoly = d1 + d2 * dfz
    D = mu * fz_n * dpoly
    dD = mu * (dpoly + fz_n * d2 / fz0)
    E = e1 + e2 * dfz
    dE = e2 / fz0
    if E > 1.0:
        E = 1.0
        dE = 0.0
    if D <= 1e-9 or K <= 0.0:
        out[0] = 0.0
        out[1] = 0.0
        out[2] = 0.0
        return
    B = K / (c * D)
    dB = (dK * D - K * dD) / (c * D * D)
    u = B * s
    atu = math.atan(u)
    phi = u - E * (u - atu)
    y = c * math.atan(phi)
    sy = math.sin(y)
    g = D * math.cos(y) * c / (1.0 + phi * phi)
    dphi_du = (1.0 - E) + E / (1.0 + u * u)
    out[0] = D * sy
    out[1] = g * dphi_du * B
    out[2] = dD * sy + g * (dphi_du * s * dB - (u - atu) * dE)


@njit
def _seven_prepare(prm, wt, delta, tt, dm, cw):
    """Per-stage constants of SevenDofPrediction._prepare into cw (58,): (ΣFX, ΣFY, Mz)
    of the quasi-steady Fx, their ∂/∂ΔM, then per wheel 13 entries
    (uw0..2, vw0..2, cx, cy, cm, Fz base N, ky_ay, c_lin, Fz cap)."""
    cd, sd = math.cos(delta), math.sin(delta)
    m, rad = prm[0], prm[2]
    ax = tt / (m * rad)
    fx_mean = tt / (4.0 * rad)
    fx_dm = dm / (4.0 * rad)
    fdm = 1.0 / (4.0 * rad)
    bx = by = bm = dx = dy = dmz = 0.0
    for i in range(4):
        xw, yw, front, fzs, kax, kay, clin, side, fzcap = (
            wt[i, 0], wt[i, 1], wt[i, 2], wt[i, 3], wt[i, 4], wt[i, 5], wt[i, 6], wt[i, 7],
            wt[i, 8])
        fx = fx_mean + side * fx_dm
        o = 6 + 13 * i
        if front != 0.0:
            cw[o], cw[o + 1], cw[o + 2] = cd, sd, -yw * cd + xw * sd
            cw[o + 3], cw[o + 4], cw[o + 5] = -sd, cd, xw * cd + yw * sd
            cw[o + 6], cw[o + 7], cw[o + 8] = -sd, cd, xw * cd + yw * sd
            fX, fY = fx * cd, fx * sd
            gX, gY = cd * side * fdm, sd * side * fdm
        else:
            cw[o], cw[o + 1], cw[o + 2] = 1.0, 0.0, -yw
            cw[o + 3], cw[o + 4], cw[o + 5] = 0.0, 1.0, xw
            cw[o + 6], cw[o + 7], cw[o + 8] = 0.0, 1.0, xw
            fX, fY = fx, 0.0
            gX, gY = side * fdm, 0.0
        bx += fX
        by += fY
        bm += xw * fY - yw * fX
        dx += gX
        dy += gY
        dmz += xw * gY - yw * gX
        cw[o + 9] = fzs + kax * ax
        cw[o + 10] = kay
        cw[o + 11] = clin
        cw[o + 12] = fzcap
    cw[0], cw[1], cw[2] = bx, by, bm
    cw[3], cw[4], cw[5] = dx, dy, dmz


@njit
def _seven_rhs_jac(vx, vy, r, prm, wt, cw, g, mfo):
    """g (15,) = (ẋ 3, ∂ẋ/∂x row-major 9, ∂ẋ/∂ΔM 3) of SevenDofPrediction._rhs_jac."""
    mu, mf, vlow, fzmin = prm[3], prm[7] != 0.0, prm[8], prm[9]
    ay = vx * r
    sx, sy, mz = cw[0], cw[1], cw[2]
    X0 = X1 = X2 = Y0 = Y1 = Y2 = M0 = M1 = M2 = 0.0
    for i in range(4):
        o = 6 + 13 * i
        uw0, uw1, uw2, vw0, vw1, vw2 = cw[o], cw[o + 1], cw[o + 2], cw[o + 3], cw[o + 4], \
            cw[o + 5]
        cx, cy, cm, fzb, kay, clin, fzcap = cw[o + 6], cw[o + 7], cw[o + 8], cw[o + 9], \
            cw[o + 10], cw[o + 11], cw[o + 12]
        uw = uw0 * vx + uw1 * vy + uw2 * r
        vw = vw0 * vx + vw1 * vy + vw2 * r
        if uw > vlow:
            den, dden = uw, 1.0
        elif uw < -vlow:
            den, dden = -uw, -1.0
        else:
            den, dden = vlow, 0.0
        alpha = math.atan2(vw, den)
        q = 1.0 / (den * den + vw * vw)
        a_v = den * q
        a_u = -vw * q * dden
        if mf:
            fz = fzb + kay * ay
            ok = 1.0
            if fz < fzmin:
                fz, ok = fzmin, 0.0
            elif fz > fzcap:
                fz, ok = fzcap, 0.0
            _mf_eval(wt, i, alpha, fz, mu, mfo)
            F, Fs, Ff = mfo[0], mfo[1], mfo[2]
            fy = -F
            kz = -Ff * kay * ok
            fy0 = -Fs * (a_v * vw0 + a_u * uw0) + kz * r
            fy1 = -Fs * (a_v * vw1 + a_u * uw1)
            fy2 = -Fs * (a_v * vw2 + a_u * uw2) + kz * vx
        else:
            fy = -clin * alpha
            fy0 = -clin * (a_v * vw0 + a_u * uw0)
            fy1 = -clin * (a_v * vw1 + a_u * uw1)
            fy2 = -clin * (a_v * vw2 + a_u * uw2)
        sx += cx * fy
        sy += cy * fy
        mz += cm * fy
        X0 += cx * fy0
        X1 += cx * fy1
        X2 += cx * fy2
        Y0 += cy * fy0
        Y1 += cy * fy1
        Y2 += cy * fy2
        M0 += cm * fy0
        M1 += cm * fy1
        M2 += cm * fy2
    im = 1.0 / prm[0]
    iz = 1.0 / prm[1]
    rr, ramp, kd = prm[4], prm[5], prm[6]
    avx = vx if vx >= 0.0 else -vx
    s = vx / ramp
    if s > 1.0:
        s, ds = 1.0, 0.0
    elif s < -1.0:
        s, ds = -1.0, 0.0
    else:
        ds = 1.0 / ramp
    res = -(rr * s + kd * vx * avx)
    dres = -(rr * ds + 2.0 * kd * avx)
    g[0] = sx * im + vy * r + res
    g[1] = sy * im - vx * r
    g[2] = mz * iz
    g[3] = X0 * im + dres
    g[4] = X1 * im + r
    g[5] = X2 * im + vy
    g[6] = Y0 * im - r
    g[7] = Y1 * im
    g[8] = Y2 * im - vx
    g[9] = M0 * iz
    g[10] = M1 * iz
    g[11] = M2 * iz
    g[12] = cw[3] * im
    g[13] = cw[4] * im
    g[14] = cw[5] * iz


@njit
def _rhs_jac(kind, z0, z1, z2, prm, wt, cw, delta, ax, dm_term, g, mfo):
    """The model's rhs+Jacobian: kind 0 bicycle, 1 seven-DoF."""
    if kind == 0:
        _bicycle_rhs_jac(z0, z1, z2, prm, delta, ax, dm_term, g)
    else:
        _seven_rhs_jac(z0, z1, z2, prm, wt, cw, g, mfo)


@njit
def _nan_stage(xbar, A, B, i):
    for c in range(3):
        xbar[i + 1, c] = np.nan
        B[i, c] = np.nan
        for d in range(3):
            A[i, c, d] = np.nan


@njit
def heun_rollout_jac(kind, x0, ubar, prm, wt, delta, tt, ts, h_max, stiff_rate, lam_max,
                     max_sub, vlow, xbar, A, B, wk):
    """x̄ (N+1, 3) from x0 along ū (N,) N·m and the discrete Jacobians A (N, 3, 3), B (N, 3)
    of model ``kind`` (0 bicycle, 1 seven-DoF; prm/wt as in the module docstring).

    delta: road-wheel angle, rad; tt: total torque, N·m; ts: step, s; h_max s, stiff_rate
    m/s², lam_max, max_sub: the sub-step rule of _substep.py; vlow: V_LOW m/s;
    wk (128,) scratch."""
    n_st = ubar.shape[0]
    ga = wk[0:15]
    gb = wk[15:30]
    S = wk[30:39]
    S1 = wk[39:48]
    JS = wk[48:57]
    mfo = wk[57:60]
    cw = wk[64:122]
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
            lam = stiff_rate / (vabs if vabs > vlow else vlow)
            n = max(math.ceil(ts / h_max - 1e-9), math.ceil(ts * lam / lam_max - 1e-9))
            n = min(max(n, 1), max_sub)
        if n == 0:
            _nan_stage(xbar, A, B, i)
            continue
        ax = 0.0
        dm_term = 0.0
        if kind == 0:
            ax = tt / (prm[0] * prm[7])
            dm_term = prm[6] * dm
        else:
            _seven_prepare(prm, wt, delta, tt, dm, cw)
        h = ts / n
        hh = 0.5 * h
        for k in range(9):
            S[k] = 0.0
        S[0] = 1.0
        S[4] = 1.0
        S[8] = 1.0
        sb0, sb1, sb2 = 0.0, 0.0, 0.0
        for _ in range(n):
            _rhs_jac(kind, z0, z1, z2, prm, wt, cw, delta, ax, dm_term, ga, mfo)
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
            _rhs_jac(kind, z0 + h * ga[0], z1 + h * ga[1], z2 + h * ga[2], prm, wt, cw, delta,
                     ax, dm_term, gb, mfo)
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
            _nan_stage(xbar, A, B, i)
            continue
        xbar[i + 1, 0], xbar[i + 1, 1], xbar[i + 1, 2] = z0, z1, z2
        for rr in range(3):
            for cc in range(3):
                A[i, rr, cc] = S[3 * rr + cc]
        B[i, 0], B[i, 1], B[i, 2] = sb0, sb1, sb2
