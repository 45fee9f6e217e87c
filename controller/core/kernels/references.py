"""Compiled Algorithm 1 search (reference: ``RhonnReferences._grid``, ``._newton`` and the
radius rounds of ``.compute`` in references/algorithm1.py).

``algorithm1_search`` runs the bounded rounds: per round the n×n grid over the
neighbourhood ∩ limits (cost + ε_t·d² selection, ties to the first node in row-major
order as ``np.argmin``), then ≤ newton_iters damped Newton steps; stop at cost ≤ ε_t, or
when the whole feasible box was searched, or after max_rounds. The same operations in the
same order as the numpy reference, in float64.

cfg (9,): [η (m/s)/(rad/s), ε_t m/s, rs0_vy m/s, rs0_r rad/s, drs_vy m/s, drs_r rad/s,
max_rounds, newton_iters, increment form (1/0)]; sm (4,): [μ2, β2, μ3, β3] of the tanh
scalings S(Vy), S(ωr); unit (n,): the grid's nodes on [−1, 1]; coef (3, 4): the bilinear
coefficients (RhonnModel.bilinear_coefficients); out (5,): [Vyd m/s, ωrd rad/s, cost m/s,
rounds, not converged (1/0)]; wk (4n,) scratch.
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.kernels import njit
from controller.core.kernels.mpc import bilinear_coefficients


@njit
def _residual(coef, sm, inc, vy, r):
    """(F_vy − Vy, F_r − ωr) of the increment / absolute map at one point."""
    a = sm[0] * math.tanh(sm[1] * vy)
    b = sm[2] * math.tanh(sm[3] * r)
    gv = coef[1, 0] + coef[1, 1] * a + coef[1, 2] * b + coef[1, 3] * a * b
    gr = coef[2, 0] + coef[2, 1] * a + coef[2, 2] * b + coef[2, 3] * a * b
    if not inc:
        gv -= vy
        gr -= r
    return gv, gr


@njit
def _grid(coef, sm, inc, eta, eps_t, unit, lo_v, hi_v, lo_r, hi_r, cv, cr, rv, rr, wk):
    """(best Vy, best ωr, its raw cost) over the grid; see RhonnReferences._grid."""
    n = unit.shape[0]
    nv = wk[0:n]
    nr = wk[n:2 * n]
    xa = wk[2 * n:3 * n]
    xb = wk[3 * n:4 * n]
    hv, hr = 0.5 * (hi_v - lo_v), 0.5 * (hi_r - lo_r)
    mv, mr = lo_v + hv, lo_r + hr
    for k in range(n):
        nv[k] = unit[k] * hv + mv
        nr[k] = unit[k] * hr + mr
        xa[k] = np.tanh(nv[k] * sm[1]) * sm[0]
        xb[k] = np.tanh(nr[k] * sm[3]) * sm[2]
    irv = 1.0 / rv
    irr = 1.0 / rr
    best = np.inf
    bi, bj = 0, 0
    bcost = np.nan
    found_nan = False
    for i in range(n):
        a = xa[i]
        t2v = coef[1, 3] * a + coef[1, 2]
        t2r = coef[2, 3] * a + coef[2, 2]
        t1v = coef[1, 1] * a + coef[1, 0]
        t1r = coef[2, 1] * a + coef[2, 0]
        dv = (nv[i] - cv) * irv
        dv = dv * dv
        for j in range(n):
            g0 = t2v * xb[j] + t1v
            g1 = t2r * xb[j] + t1r
            if not inc:
                g0 -= nv[i]
                g1 -= nr[j]
            cost = abs(g0) + abs(g1) * eta
            dr = (nr[j] - cr) * irr
            sel = (dv + dr * dr) * eps_t + cost
            if sel != sel:          # np.argmin returns the first NaN
                bi, bj, bcost = i, j, cost
                found_nan = True
                break
            if sel < best:
                best = sel
                bi, bj, bcost = i, j, cost
        if found_nan:
            break
    if not found_nan and best == np.inf:   # all +inf: argmin's first node
        g0, g1 = _grid_cost_at(coef, inc, xa[0], xb[0], nv[0], nr[0])
        bcost = abs(g0) + abs(g1) * eta
    return nv[bi], nr[bj], bcost


@njit
def _grid_cost_at(coef, inc, a, b, v, r):
    g0 = (coef[1, 3] * a + coef[1, 2]) * b + (coef[1, 1] * a + coef[1, 0])
    g1 = (coef[2, 3] * a + coef[2, 2]) * b + (coef[2, 1] * a + coef[2, 0])
    if not inc:
        g0 -= v
        g1 -= r
    return g0, g1


@njit
def _newton(coef, sm, inc, eta, eps_t, iters, vy, r, cost, lo_v, hi_v, lo_r, hi_r):
    """Bounded Newton polish inside the box; see RhonnReferences._newton."""
    for _ in range(iters):
        gv, gr = _residual(coef, sm, inc, vy, r)
        a = sm[0] * math.tanh(sm[1] * vy)
        b = sm[2] * math.tanh(sm[3] * r)
        ta = math.tanh(sm[1] * vy)
        da = sm[0] * sm[1] * (1.0 - ta * ta)
        tb = math.tanh(sm[3] * r)
        db = sm[2] * sm[3] * (1.0 - tb * tb)
        j11 = (coef[1, 1] + coef[1, 3] * b) * da
        j12 = (coef[1, 2] + coef[1, 3] * a) * db
        j21 = (coef[2, 1] + coef[2, 3] * b) * da
        j22 = (coef[2, 2] + coef[2, 3] * a) * db
        if not inc:
            j11 -= 1.0
            j22 -= 1.0
        det = j11 * j22 - j12 * j21
        if not math.isfinite(det) or abs(det) < 1e-12:
            break
        nv = min(max(vy - (j22 * gv - j12 * gr) / det, lo_v), hi_v)
        nr = min(max(r - (j11 * gr - j21 * gv) / det, lo_r), hi_r)
        ngv, ngr = _residual(coef, sm, inc, nv, nr)
        ncost = abs(ngv) + eta * abs(ngr)
        if not ncost < cost:
            break
        vy, r, cost = nv, nr, ncost
        if cost <= eps_t:
            break
    return vy, r, cost


@njit
def algorithm1_search(coef, sm, cfg, unit, cv, cr, v_lim, r_lo, r_hi, out, wk):
    """Radius rounds of Algorithm 1 from the centre (cv m/s, cr rad/s) inside
    |Vy| ≤ v_lim m/s, r_lo ≤ ωr ≤ r_hi rad/s; result into out (see the module docstring)."""
    eta, eps_t = cfg[0], cfg[1]
    max_rounds, iters, inc = int(cfg[6]), int(cfg[7]), cfg[8] != 0.0
    bv, br, bc = cv, cr, np.inf
    rounds = 0
    nc = 1.0
    for k in range(max_rounds):
        rounds = k + 1
        rv = cfg[2] + k * cfg[4]
        rr = cfg[3] + k * cfg[5]
        lo_v, hi_v = max(cv - rv, -v_lim), min(cv + rv, v_lim)
        lo_r, hi_r = max(cr - rr, r_lo), min(cr + rr, r_hi)
        gv, gr, gc = _grid(coef, sm, inc, eta, eps_t, unit, lo_v, hi_v, lo_r, hi_r, cv, cr,
                           rv, rr, wk)
        gv, gr, gc = _newton(coef, sm, inc, eta, eps_t, iters, gv, gr, gc, lo_v, hi_v, lo_r,
                             hi_r)
        if gc < bc:
            bv, br, bc = gv, gr, gc
        if bc <= eps_t:
            nc = 0.0
            break
        if lo_v <= -v_lim and hi_v >= v_lim and lo_r <= r_lo and hi_r >= r_hi:
            break
    out[0], out[1], out[2], out[3], out[4] = bv, br, bc, rounds, nc


@njit
def demand_blend(vx, vy, yaw_rate, delta_w, ay, env_d, dw_prev, env_a, prm, W, mono, tfac,
                 w4, coef, a1cfg, sm, unit, wk, a1out, out):
    """One call of the default nmpc-rhonn references (reference: ``BlendedReferences``
    with ``BicycleDemand`` in references/intent.py, ``LinearReferences`` in linear.py and
    ``RhonnReferences.compute`` in algorithm1.py with the live weights, slow_tau_s = 0).

    vx, vy m/s, yaw_rate rad/s, delta_w rad, ay m/s²; env_d, dw_prev: BicycleDemand's |ay|
    envelope m/s² and last δw rad; env_a: Algorithm 1's |ay| envelope m/s². W, mono, tfac,
    w4, coef: as kernels.mpc.bilinear_coefficients; a1cfg, sm, unit, wk, a1out: as
    algorithm1_search. prm (25,): [demand decay, ts s, intent_lead_s s, intent_ay_margin,
    ay_floor m/s², ay_ceiling m/s², v_min m/s, K s²/m², L m, lr m, β_k s²/m, DEN_MIN,
    MAX_SPEED m/s, MAX_STEER rad, Algorithm-1 decay, ay_margin, tan(beta_max),
    r_kin_factor, r_band rad/s, μ and β of S(Vx), μ and β of S(δw), blend β_lo rad,
    β_hi rad, sideslip guard on (1/0), guard β threshold rad, guard gain 1/s] (indices
    0–27; the guard is references/sideslip_guard.py ``SideslipGuard.compute`` with
    v_min = prm[6]). out (11,): [ωrd rad/s, Vyd m/s, βd rad, env_d, dw_prev, env_a,
    not converged (1/0), rounds (−1: no search this call), cost m/s, blend weight,
    guard changed ωrd (1/0)]."""
    # --- BicycleDemand (linear bicycle + lead + grip cap)
    if math.isfinite(ay):
        env_d = max(abs(ay), env_d * prm[0])
    if not (abs(vx) <= prm[12] and abs(delta_w) <= prm[13]):
        ri, vi = 0.0, 0.0
    else:
        v2 = vx * vx
        den = 1.0 + prm[7] * v2
        if den < prm[11]:
            den = prm[11]
        ri = vx * delta_w / (prm[8] * den)
        beta_ss = delta_w * (prm[9] - prm[10] * v2) / (prm[8] * den)
        vi = beta_ss * vx
    if math.isfinite(delta_w):
        rate = 0.0 if math.isnan(dw_prev) else (delta_w - dw_prev) / prm[1]
        dw_prev = delta_w
        if prm[2] > 0.0 and abs(delta_w) > 1e-5:
            ri += prm[2] * (ri / delta_w) * rate
        if prm[3] > 0.0 and vx > prm[6]:
            a_max = min(max(prm[3] * env_d, prm[4]), prm[5])
            ri = min(max(ri, -a_max / vx), a_max / vx)
    # --- Algorithm 1 (RhonnReferences.compute)
    if math.isfinite(ay):
        env_a = max(abs(ay), env_a * prm[14])
    nc = 0.0
    rounds = -1.0
    cost = 0.0
    v_min = prm[6]
    if not (math.isfinite(vx) and math.isfinite(delta_w)):
        ra, va = 0.0, 0.0
    else:
        vyc = vy if math.isfinite(vy) else 0.0
        rc = yaw_rate if math.isfinite(yaw_rate) else 0.0
        if vx < v_min:
            ra = max(vx, 0.0) * delta_w / prm[8]
            va = prm[9] * ra
        else:
            r_lim = min(max(prm[15] * env_a, prm[4]), prm[5]) / vx
            v_lim = prm[16] * vx
            r_kin = prm[17] * vx * delta_w / prm[8]
            r_lo = max(min(r_kin, 0.0) - prm[18], -r_lim)
            r_hi = min(max(r_kin, 0.0) + prm[18], r_lim)
            a = prm[19] * math.tanh(prm[20] * vx)
            d = prm[21] * math.tanh(prm[22] * delta_w)
            bilinear_coefficients(W, mono, tfac, a, d, w4, coef)
            cv = min(max(vyc, -v_lim), v_lim)
            cr = min(max(rc, r_lo), r_hi)
            algorithm1_search(coef, sm, a1cfg, unit, cv, cr, v_lim, r_lo, r_hi, a1out, wk)
            va, ra, cost, rounds, nc = a1out[0], a1out[1], a1out[2], a1out[3], a1out[4]
            if not (math.isfinite(va) and math.isfinite(ra)):
                va, ra = cv, cr
    # --- blend by the measured |β|
    beta = abs(vy) / max(vx, v_min) if math.isfinite(vy) and math.isfinite(vx) else 0.0
    span = max(prm[24] - prm[23], 1e-6)
    w = min(max((beta - prm[23]) / span, 0.0), 1.0)
    r_d = (1.0 - w) * ri + w * ra
    vy_d = (1.0 - w) * vi + w * va
    b_d = vy_d / max(vx, v_min)
    # --- sideslip guard (SideslipGuard.compute): ωrd held where β shrinks at k·excess
    active = 0.0
    if prm[25] != 0.0 and vx > v_min and math.isfinite(vy) and math.isfinite(ay):
        beta_m = vy / vx
        excess = abs(beta_m) - prm[26]
        if excess > 0.0:
            s = 1.0 if beta_m > 0.0 else -1.0
            r_lim = ay / vx + s * prm[27] * excess
            if s * r_d < s * r_lim:
                r_d = r_lim
                active = 1.0
    out[0], out[1], out[2] = r_d, vy_d, b_d
    out[3], out[4], out[5] = env_d, dw_prev, env_a
    out[6], out[7], out[8], out[9], out[10] = nc, rounds, cost, w, active

