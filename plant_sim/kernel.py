"""Compiled (numba) kernel of the vehicle step: tyres + wheels + motors + body.

The same arithmetic as :meth:`plant_sim.body.VehicleModel.advance` and
:meth:`plant_sim.tyre.MagicFormulaTyre.forces_with_slope`, statement by statement and in the
same order, compiled without ``fastmath`` (no reassociation, no fused multiply-add), with the
transcendental functions from the same C library: the truth trace is bit-identical to the
pure-Python model (a test compares them). Used for uniform road friction; friction patches
(a Python lookup per wheel and step) keep the Python path.

``RHONN_PLANT_KERNEL=python`` forces the pure-Python model (for comparisons); without numba
the Python model is used as well. Units as in ``plant_sim/body.py``.
"""

from __future__ import annotations

import math
import os

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - numba is optional (the plant extra)
    numba = None

# state vector layout (float64): scalars of VehicleModel
X, Y, PSI, VX, VY, YAWRATE, PHI, DPHI, THETA, DTHETA, AX, AY, DELTA = range(13)
N_STATE = 13
# per-wheel rows of the (8, 4) wheel array
OMEGA, ALPHA_T, KAPPA_T, TORQUE, FZ, FX, FY, MU = range(8)
# constants vector layout
(C_DT, C_M, C_IZ, C_R, C_HW, C_G, C_MS, C_MUTOT, C_HRA, C_HPA, C_HPHI, C_HTHETA, C_KPHI,
 C_CPHI, C_KTH, C_CTH, C_CHI, C_IPHI, C_ITH, C_L, C_INVWB, C_MSF, C_MSR, C_MUAX, C_DRAGK,
 C_FRR, C_VRR, C_VLOW, C_SIGAF, C_SIGAR, C_SIGKF, C_SIGKR, C_LAG, C_TPK, C_PPK, C_WBASE,
 C_WFADE, C_MAXDELTA, C_FZMAXF, C_FZMAXR) = range(40)
N_CONST = 40
FZ_MIN_N = 1.0  # as plant_sim.tyre._FZ_MIN_N
MU_MIN = 1e-3  # as plant_sim.tyre._MU_MIN


def enabled() -> bool:
    """True when the compiled kernel is available and not switched off."""
    return numba is not None and os.environ.get("RHONN_PLANT_KERNEL", "numba") != "python"


def _tyre(kappa: float, alpha_rad: float, fz_n: float, mu_x: float, mu_y: float,
          p: np.ndarray, fz_max: float) -> tuple[float, float, float]:
    """``MagicFormulaTyre.forces_with_slope`` on the coefficient vector ``p`` (its ``_p``)."""
    if not fz_n > FZ_MIN_N:
        return 0.0, 0.0, 0.0
    fz0 = p[0]
    pcx1, pdx1, pdx2, pex1, pex2, pex3, pex4 = p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    pkx1, pkx2, pkx3, phx1, phx2, rbx1, rbx2 = p[8], p[9], p[10], p[11], p[12], p[13], p[14]
    rcx1, rhx1, pcy1, pdy1, pdy2, pey1, pey2 = p[15], p[16], p[17], p[18], p[19], p[20], p[21]
    pey3, pky1, pky2, phy1, phy2, pvy1, pvy2 = p[22], p[23], p[24], p[25], p[26], p[27], p[28]
    rby1, rby2, rby3, rcy1, rhy1, rhy2, rvy1 = p[29], p[30], p[31], p[32], p[33], p[34], p[35]
    rvy2, rvy4, rvy5, rvy6 = p[36], p[37], p[38], p[39]
    fz = fz_n if fz_n < fz_max else fz_max
    if mu_x < MU_MIN:
        mu_x = MU_MIN
    if mu_y < MU_MIN:
        mu_y = MU_MIN
    if kappa != kappa:
        kappa = 0.0
    if alpha_rad != alpha_rad:
        alpha_rad = 0.0
    clamped = kappa > 1.0 or kappa < -1.0
    if kappa > 1.0:
        kappa = 1.0
    elif kappa < -1.0:
        kappa = -1.0
    if alpha_rad > 1.5:
        alpha_rad = 1.5
    elif alpha_rad < -1.5:
        alpha_rad = -1.5
    dfz = (fz - fz0) / fz0

    kx = kappa + phx1 + phx2 * dfz
    dx = (pdx1 + pdx2 * dfz) * mu_x * fz
    kxk = fz * (pkx1 + pkx2 * dfz) * math.exp(pkx3 * dfz)
    bx = kxk / (pcx1 * dx)
    ex = (pex1 + pex2 * dfz + pex3 * dfz * dfz) * (1.0 - pex4 * (1.0 if kx >= 0.0 else -1.0))
    if ex > 1.0:
        ex = 1.0
    bxk = bx * kx
    phi_x = bxk - ex * (bxk - math.atan(bxk))
    cx_phi = pcx1 * math.atan(phi_x)
    fx0 = dx * math.sin(cx_phi)
    if clamped:
        dfx0 = 0.0
    else:
        dfx0 = dx * math.cos(cx_phi) * pcx1 / (1.0 + phi_x * phi_x) * bx * (
            1.0 - ex + ex / (1.0 + bxk * bxk))

    shy = phy1 + phy2 * dfz
    ay = alpha_rad + shy
    dy = (pdy1 + pdy2 * dfz) * mu_y * fz
    u = fz / (pky2 * fz0)
    kya = pky1 * fz0 * 2.0 * u / (1.0 + u * u)
    by = kya / (pcy1 * dy)
    ey = (pey1 + pey2 * dfz) * (1.0 - pey3 * (1.0 if ay >= 0.0 else -1.0))
    if ey > 1.0:
        ey = 1.0
    bya = by * ay
    fy0 = dy * math.sin(pcy1 * math.atan(bya - ey * (bya - math.atan(bya)))) + (
        pvy1 + pvy2 * dfz) * mu_y * fz

    t = rbx2 * kappa
    bxa = rbx1 / math.sqrt(1.0 + t * t)
    a_s = alpha_rad + rhx1
    gxa = math.cos(rcx1 * math.atan(bxa * a_s)) / math.cos(rcx1 * math.atan(bxa * rhx1))
    t = rby2 * (alpha_rad - rby3)
    byk = rby1 / math.sqrt(1.0 + t * t)
    shyk = rhy1 + rhy2 * dfz
    gyk = math.cos(rcy1 * math.atan(byk * (kappa + shyk))) / math.cos(
        rcy1 * math.atan(byk * shyk))
    ra = rvy4 * alpha_rad
    dvyk = mu_y * fz * (rvy1 + rvy2 * dfz) / math.sqrt(1.0 + ra * ra)
    svyk = dvyk * math.sin(rvy5 * math.atan(rvy6 * kappa)) if dvyk != 0.0 else 0.0
    return gxa * fx0, gyk * fy0 + svyk, gxa * dfx0


def _advance(deltas: np.ndarray, cmd: np.ndarray, s: np.ndarray, wh: np.ndarray,
             c: np.ndarray, tyre_p: np.ndarray, wxs: np.ndarray, wys: np.ndarray,
             fz_st: np.ndarray) -> None:
    """``VehicleModel.advance`` with uniform friction (``wh[MU]`` already set); updates the
    state ``s`` and the wheel array ``wh`` in place."""
    dt = c[C_DT]
    m = c[C_M]
    Iz = c[C_IZ]
    R = c[C_R]
    h_w = c[C_HW]
    g = c[C_G]
    ms = c[C_MS]
    mu_tot = c[C_MUTOT]
    hra, hpa = c[C_HRA], c[C_HPA]
    hphi, htheta = c[C_HPHI], c[C_HTHETA]
    k_phi, c_phi = c[C_KPHI], c[C_CPHI]
    k_th, c_th = c[C_KTH], c[C_CTH]
    chi = c[C_CHI]
    I_phi, I_th = c[C_IPHI], c[C_ITH]
    L = c[C_L]
    inv_wb = c[C_INVWB]
    ms_f, ms_r = c[C_MSF], c[C_MSR]
    mu_ax = c[C_MUAX]
    drag_k = c[C_DRAGK]
    f_rr = c[C_FRR]
    v_rr = c[C_VRR]
    v_low = c[C_VLOW]
    lag = c[C_LAG]
    t_pk, p_pk, w_base = c[C_TPK], c[C_PPK], c[C_WBASE]
    w_fade = c[C_WFADE]
    max_delta = c[C_MAXDELTA]

    x, y, psi = s[X], s[Y], s[PSI]
    vx, vy, r = s[VX], s[VY], s[YAWRATE]
    phi, dphi, theta, dtheta = s[PHI], s[DPHI], s[THETA], s[DTHETA]
    ax, ay = s[AX], s[AY]
    delta = s[DELTA]
    omega, alpha_t, kappa_t, torque = wh[OMEGA], wh[ALPHA_T], wh[KAPPA_T], wh[TORQUE]
    fz_out, fx_out, fy_out, mu_out = wh[FZ], wh[FX], wh[FY], wh[MU]

    for k in range(deltas.shape[0]):
        delta_in = deltas[k]
        if -max_delta <= delta_in <= max_delta:
            delta = delta_in
        else:
            delta = max_delta if delta_in > 0 else -max_delta
        cd, sd = math.cos(delta), math.sin(delta)
        cpsi, spsi = math.cos(psi), math.sin(psi)

        m_theta = k_th * theta + c_th * dtheta
        d_long = (ms * hpa * ax + mu_tot * R * ax - m_theta) / L
        m_phi = k_phi * phi + c_phi * dphi
        d_lat_f = (chi * m_phi + ms_f * hra * ay + mu_ax * R * ay) * inv_wb
        d_lat_r = ((1.0 - chi) * m_phi + ms_r * hra * ay + mu_ax * R * ay) * inv_wb
        fz0 = fz_st[0] - 0.5 * d_long - d_lat_f
        fz1 = fz_st[1] - 0.5 * d_long + d_lat_f
        fz2 = fz_st[2] + 0.5 * d_long - d_lat_r
        fz3 = fz_st[3] + 0.5 * d_long + d_lat_r
        fz_out[0] = fz0 if fz0 > 0.0 else 0.0
        fz_out[1] = fz1 if fz1 > 0.0 else 0.0
        fz_out[2] = fz2 if fz2 > 0.0 else 0.0
        fz_out[3] = fz3 if fz3 > 0.0 else 0.0

        sum_fx = 0.0
        sum_fy = 0.0
        mz = 0.0
        for i in range(4):
            wx, wy = wxs[i], wys[i]
            fz = fz_out[i]
            mu = mu_out[i]
            vxi = vx - r * wy
            vyi = vy + r * wx
            if i < 2:
                vxw = vxi * cd + vyi * sd
                vyw = vyi * cd - vxi * sd
                axle = 0
                sig_a, sig_k = c[C_SIGAF], c[C_SIGKF]
                fz_max = c[C_FZMAXF]
            else:
                vxw, vyw = vxi, vyi
                axle = 1
                sig_a, sig_k = c[C_SIGAR], c[C_SIGKR]
                fz_max = c[C_FZMAXR]
            avx = vxw if vxw >= 0.0 else -vxw
            den = avx if avx > v_low else v_low
            speed = math.sqrt(vxw * vxw + vyw * vyw)
            if speed < v_low:
                speed = v_low
            a_a = dt * speed / sig_a
            at = (alpha_t[i] + a_a * math.atan2(vyw, den)) / (1.0 + a_a)
            alpha_t[i] = at
            w = omega[i]
            kt = kappa_t[i]
            fxw, fyw, slope = _tyre_c(kt, at, fz, mu, mu, tyre_p[axle], fz_max)
            if slope < 0.0:
                slope = 0.0

            tq = torque[i] + (cmd[i] - torque[i]) * lag
            aw = w if w >= 0.0 else -w
            t_max = t_pk if aw <= w_base else p_pk / aw
            fade = w / w_fade
            t_min = -t_max * (0.0 if fade < 0.0 else (1.0 if fade > 1.0 else fade))
            tq = t_max if tq > t_max else (t_min if tq < t_min else tq)
            torque[i] = tq

            s_rr = w * R / v_rr
            s_rr = 1.0 if s_rr > 1.0 else (-1.0 if s_rr < -1.0 else s_rr)
            f_net = tq - R * fxw - f_rr * fz * R * s_rr

            a_k = dt * speed / sig_k
            c_k = R / den
            e_k = (w * R - vxw) / den - kt
            gk = h_w * R * slope * a_k / (1.0 + a_k)
            d_w = (h_w * f_net - gk * e_k) / (1.0 + gk * c_k)
            omega[i] = w + d_w
            kappa_t[i] = kt + a_k * (e_k + c_k * d_w) / (1.0 + a_k)

            fx_out[i] = fxw
            fy_out[i] = fyw
            if i < 2:
                fxb = fxw * cd - fyw * sd
                fyb = fxw * sd + fyw * cd
            else:
                fxb, fyb = fxw, fyw
            sum_fx += fxb
            sum_fy += fyb
            mz += wx * fyb - wy * fxb

        ax = (sum_fx - drag_k * vx * (vx if vx >= 0.0 else -vx)) / m
        ay = sum_fy / m
        vx += dt * (ax + r * vy)
        vy += dt * (ay - r * vx)
        r += dt * mz / Iz
        psi += dt * r
        x += dt * (vx * cpsi - vy * spsi)
        y += dt * (vx * spsi + vy * cpsi)
        dphi += dt * (ms * hphi * (ay + g * phi) - k_phi * phi - c_phi * dphi) / I_phi
        phi += dt * dphi
        dtheta += dt * (ms * htheta * (g * theta - ax) - k_th * theta - c_th * dtheta) / I_th
        theta += dt * dtheta

    s[X], s[Y], s[PSI] = x, y, psi
    s[VX], s[VY], s[YAWRATE] = vx, vy, r
    s[PHI], s[DPHI], s[THETA], s[DTHETA] = phi, dphi, theta, dtheta
    s[AX], s[AY] = ax, ay
    s[DELTA] = delta


if numba is not None:
    # error_model="python": division by zero raises like CPython instead of giving inf;
    # fastmath stays off (the default), so the arithmetic is IEEE as in CPython.
    _tyre_c = numba.njit(cache=True, error_model="python")(_tyre)
    advance_kernel = numba.njit(cache=True, error_model="python")(_advance)
else:  # pragma: no cover
    _tyre_c = _tyre
    advance_kernel = _advance
