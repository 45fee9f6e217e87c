"""Compiled torque allocation (reference: ``controller.core.allocation.TorqueAllocator``).

``motor_limits`` and ``allocate`` do the same operations as the reference methods of the
same names (including ``front_share`` and ``_split``), in the dtype of ``prm``/``out``
(scalars are cast to it on entry).
prm (13,): [T_peak N·m, P_peak W, equal split (0/1), acc_clip m/s², mass kg, wheelbase
m, cg height m, track m, lf m, lr m, static front axle load N, static rear axle load N,
fz_floor_frac -].
"""

from __future__ import annotations

import numpy as np

from controller.core.kernels import njit


@njit
def motor_limits(ws, prm, lim):
    """lim (4,) = min(T_peak, P_peak/|ω_i|) N·m (T_peak for a non-finite or zero ω_i)."""
    tp, pp = prm[0], prm[1]
    for i in range(4):
        w = abs(ws[i])
        if np.isfinite(w) and w > 0.0:
            lim[i] = min(tp, pp / w)
        else:
            lim[i] = tp


@njit
def dm_capacity(ws, prm, lim):
    """motor_limits into lim, then 2·min(lim₁ + lim₃, lim₂ + lim₄) N·m (reference:
    ``TorqueAllocator.delta_m_capacity``; sums in lim's dtype)."""
    motor_limits(ws, prm, lim)
    return 2.0 * min(lim[0] + lim[2], lim[1] + lim[3])


@njit
def _split(t_side, front, lim_f, lim_r):
    tf = t_side * front
    if tf > lim_f:
        tf = lim_f
    elif tf < -lim_f:
        tf = -lim_f
    tr = t_side - tf
    if tr > lim_r:
        tr = lim_r
        tf = t_side - tr
    elif tr < -lim_r:
        tr = -lim_r
        tf = t_side - tr
    tf = min(max(tf, -lim_f), lim_f)
    return tf, tr


@njit
def allocate(tt_in, dm_in, ax_in, ay_in, ws, lim, limits_current, prm, out):
    """Wheel torques out (4,) N·m for Tt, ΔM N·m; returns the realised (Tt, ΔM) N·m."""
    if not limits_current:
        motor_limits(ws, prm, lim)
    dt = prm.dtype.type
    zero = dt(0.0)
    half = dt(0.5)
    two = dt(2.0)
    tt = dt(tt_in)
    dm = dt(dm_in)
    ax = dt(ax_in)
    ay = dt(ay_in)
    cl = lim[0] + lim[2]
    cr = lim[1] + lim[3]
    if not np.isfinite(dm):
        dm = zero
    if not np.isfinite(tt):
        tt = zero
    dm = min(max(dm, -(cl + cr)), cl + cr)
    tt_lo = max(-two * cr - dm, dm - two * cl)
    tt_hi = min(two * cr - dm, dm + two * cl)
    tt = min(max(tt, tt_lo), tt_hi)
    t_left = half * (tt - dm)
    t_right = half * (tt + dm)
    t_left = min(max(t_left, -cl), cl)
    t_right = min(max(t_right, -cr), cr)
    if prm[2] != 0.0:
        sl, sr = half, half
    else:
        clip = prm[3]
        m, L, h, wb, lf, lr = prm[4], prm[5], prm[6], prm[7], prm[8], prm[9]
        fzf_s, fzr_s, ffrac = prm[10], prm[11], prm[12]
        axc = ax if np.isfinite(ax) else zero
        ayc = ay if np.isfinite(ay) else zero
        axc = min(max(axc, -clip), clip)
        ayc = min(max(ayc, -clip), clip)
        dlong = m * axc * h / L
        fzf = fzf_s - dlong
        fzr = fzr_s + dlong
        dlat = m * ayc * h / wb
        dlf = dlat * lr / L
        dlr = dlat * lf / L
        ff, fr = ffrac * fzf_s / two, ffrac * fzr_s / two
        fz1 = max(fzf / two - dlf / two, ff)
        fz2 = max(fzf / two + dlf / two, ff)
        fz3 = max(fzr / two - dlr / two, fr)
        fz4 = max(fzr / two + dlr / two, fr)
        sl, sr = fz1 / (fz1 + fz3), fz2 / (fz2 + fz4)
    out[0], out[2] = _split(t_left, sl, lim[0], lim[2])
    out[1], out[3] = _split(t_right, sr, lim[1], lim[3])
    return t_left + t_right, t_right - t_left
