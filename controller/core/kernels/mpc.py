"""Compiled linearisation, condensing and QP data of the MPC (reference: mpc/qp.py and
model/rhonn.py ``RhonnModel.rollout_linearize``).

* ``rhonn_rollout_jac``: parallel RHONN rollout x̄ (N+1, 3) and Jacobians A (N, 3, 3),
  B (N, 3) — the same operations as ``rollout_linearize``.
* ``condense_build``: sensitivities S, output Jacobian G, ȳ, and the QP data P (dense and
  CSC upper-triangle values) and q — ``LinearizedMpc._linearise`` (after the model) +
  ``LinearizedMpc._build`` + the finiteness/magnitude check of ``solve``.
* ``warm_start`` / ``accept``: the shifted nominal input before, and the box clip of the
  OSQP iterate after, the solve.
All work in the dtype of their arrays: scalar arguments (Python floats) are cast to it
on entry.
"""

from __future__ import annotations

import numpy as np

from controller.core.kernels import njit


@njit
def rhonn_rollout_jac(x0, ubar, W, mu, be, kt, kd, kp, u_prev, dw, inc, deriv, phi_ext,
                      dxi, wx, xbar, A, B):
    """x̄ and the Jacobians of the RHONN along ū (N,) N·m from x0 (3,) [m/s, m/s, rad/s].

    W (3, 15); mu, be (4,) tanh scaling; kt: Ts·Tt/(m r), m/s; kd, kp: (rad/s)/(N·m) gains
    of ΔM_i and ΔM_{i−1}; u_prev: applied ΔM, N·m; dw: δw, rad; inc: increment form;
    deriv (3, 15) index table into φ_ext = [1, φ, 0] (17,); dxi, wx (3,) scratch."""
    n = ubar.shape[0]
    dt = W.dtype.type
    zero = dt(0.0)
    one = dt(1.0)
    kt_, kd_, kp_, up = dt(kt), dt(kd), dt(kp), dt(u_prev)
    d = mu[3] * np.tanh(be[3] * dt(dw))
    x0f, x1f, x2f = x0[0], x0[1], x0[2]
    xbar[0, 0], xbar[0, 1], xbar[0, 2] = x0f, x1f, x2f
    phi_ext[0] = one
    phi_ext[16] = zero
    for i in range(n):
        ta = np.tanh(be[0] * x0f)
        tb = np.tanh(be[1] * x1f)
        tc = np.tanh(be[2] * x2f)
        a, b, c = mu[0] * ta, mu[1] * tb, mu[2] * tc
        ab, ac, ad, bc, bd, cd = a * b, a * c, a * d, b * c, b * d, c * d
        abc = ab * c
        phi_ext[1], phi_ext[2], phi_ext[3], phi_ext[4] = a, b, c, d
        phi_ext[5], phi_ext[6], phi_ext[7] = ab, ac, ad
        phi_ext[8], phi_ext[9], phi_ext[10] = bc, bd, cd
        phi_ext[11], phi_ext[12], phi_ext[13] = abc, ab * d, ac * d
        phi_ext[14], phi_ext[15] = bc * d, abc * d
        dxi[0] = mu[0] * be[0] * (one - ta * ta)
        dxi[1] = mu[1] * be[1] * (one - tb * tb)
        dxi[2] = mu[2] * be[2] * (one - tc * tc)
        for r in range(3):
            w0 = zero
            for k in range(15):
                w0 += W[r, k] * phi_ext[k + 1]
            wx[r] = w0
            for j in range(3):
                acc = zero
                for k in range(15):
                    acc += W[r, k] * (phi_ext[deriv[j, k]] * dxi[j])
                A[i, r, j] = acc + one if (inc and r == j) else acc
        wx0, wx1, wx2 = wx[0], wx[1], wx[2]
        ui = ubar[i]
        if inc:
            x0f = x0f + kt_ + wx0
            x1f = x1f + wx1
            x2f = x2f + kd_ * ui + kp_ * up + wx2
        else:
            x0f = kt_ + wx0
            x1f = wx1
            x2f = kd_ * ui + kp_ * up + wx2
        up = ui
        xbar[i + 1, 0], xbar[i + 1, 1], xbar[i + 1, 2] = x0f, x1f, x2f
        B[i, 0] = zero
        B[i, 1] = zero
        B[i, 2] = kd_


@njit
def warm_start(sol, ubar, dm_min, dm_max, yd, yaw_ref, beta_ref):
    """ū = previous solution shifted one stage (last repeated), clipped to the box, N·m;
    y_d = [ωrd, βd] per stage."""
    n = ubar.shape[0]
    dt = ubar.dtype.type
    lo, hi, yr, br = dt(dm_min), dt(dm_max), dt(yaw_ref), dt(beta_ref)
    for i in range(n - 1):
        ubar[i] = sol[i + 1]
    ubar[n - 1] = sol[n - 1]
    for i in range(n):
        ubar[i] = min(max(ubar[i], lo), hi)
        yd[2 * i] = yr
        yd[2 * i + 1] = br


@njit
def condense_build(xbar, A, B, bp, has_bp, v_min, us, wdiag, reg, yd, ubar, tri_r, tri_c,
                   S, G, ybar, Pd, Px, q, limit):
    """Sensitivities S (N, nx, N), G (2N, N), ȳ (2N,), P (N, N) / Px and q of the QP.

    bp (nx,): ∂x_{i+1}/∂ΔM_{i−1} (used when has_bp); v_min, m/s; us: N·m per decision
    unit; wdiag (2N,): [q_yaw, r_beta] per stage; reg: 2λ. Returns True when every entry
    of Px and q is finite and below ``limit`` in magnitude."""
    n, nx = B.shape
    dt = G.dtype.type
    zero = dt(0.0)
    two = dt(2.0)
    vmin, usc, rg, lim = dt(v_min), dt(us), dt(reg), dt(limit)
    for a in range(nx):
        for c in range(n):
            S[0, a, c] = zero
        S[0, a, 0] = B[0, a]
    for i in range(1, n):
        for a in range(nx):
            for c in range(n):
                acc = zero
                for b in range(nx):
                    acc += A[i, a, b] * S[i - 1, b, c]
                S[i, a, c] = acc
            S[i, a, i] += B[i, a]
            if has_bp:
                S[i, a, i - 1] += bp[a]
    for i in range(n):
        xv = xbar[i + 1, 0]
        vx = xv if xv > vmin else vmin            # also NaN → v_min (np.fmax)
        bb = xbar[i + 1, 1] / vx
        t = bb / vx
        for c in range(n):
            G[2 * i, c] = S[i, 2, c] * usc
            g = S[i, 1, c] / vx
            g -= S[i, 0, c] * t
            G[2 * i + 1, c] = g * usc
        ybar[2 * i] = xbar[i + 1, 2]
        ybar[2 * i + 1] = bb
    for a in range(n):
        for b in range(n):
            acc = zero
            for r in range(2 * n):
                acc += G[r, a] * (G[r, b] * wdiag[r])
            Pd[a, b] = acc * two + (rg if a == b else zero)
    ok = True
    for k in range(tri_r.shape[0]):
        v = Pd[tri_r[k], tri_c[k]]
        Px[k] = v
        if not (abs(v) < lim):
            ok = False
    for a in range(n):
        acc = zero
        for r in range(2 * n):
            gz = zero
            for c in range(n):
                gz += G[r, c] * (ubar[c] / usc)
            rhs = gz + yd[r] - ybar[r]
            acc += (G[r, a] * wdiag[r]) * rhs
        q[a] = acc * (-two)
        if not (abs(q[a]) < lim):
            ok = False
    return ok


@njit
def accept(x, lb, ub, us, z, ubar):
    """z = clip(x, lb, ub) (decision units), ū = us·z N·m; False if x is not finite."""
    s = 0.0
    for i in range(x.shape[0]):
        s += x[i]
    if not np.isfinite(s):
        return False
    usc = z.dtype.type(us)
    for i in range(x.shape[0]):
        v = max(x[i], lb[i])
        z[i] = min(v, ub[i])
        ubar[i] = z[i] * usc
    return True


@njit
def accept_sol(x, lb, ub, us, z, ubar, sol):
    """accept, and on success also sol ← ū (the accepted solution, N·m; the copy
    ``LinearizedMpc._finish`` makes)."""
    if not accept(x, lb, ub, us, z, ubar):
        return False
    for i in range(ubar.shape[0]):
        sol[i] = ubar[i]
    return True


@njit
def rhonn_predict(x0, x1, x2, W, mu, be, dw, kt, kdm, inc, phi, wx, out):
    """One RHONN step (reference: ``RhonnModel.predict``): φ (15,) of (x, δw) into phi,
    out (3,) = [x +] known + W φ. kt: Ts·Tt/(m r), m/s; kdm: known ΔM part, rad/s.
    Returns False if out is not finite."""
    dt = W.dtype.type
    a = mu[0] * np.tanh(be[0] * dt(x0))
    b = mu[1] * np.tanh(be[1] * dt(x1))
    c = mu[2] * np.tanh(be[2] * dt(x2))
    d = mu[3] * np.tanh(be[3] * dt(dw))
    ab, ac, ad, bc, bd, cd = a * b, a * c, a * d, b * c, b * d, c * d
    abc = ab * c
    phi[0], phi[1], phi[2], phi[3] = a, b, c, d
    phi[4], phi[5], phi[6], phi[7], phi[8], phi[9] = ab, ac, ad, bc, bd, cd
    phi[10], phi[11], phi[12], phi[13], phi[14] = abc, ab * d, ac * d, bc * d, abc * d
    for r in range(3):
        acc = dt(0.0)
        for k in range(15):
            acc += W[r, k] * phi[k]
        wx[r] = acc
    if inc:
        out[0] = dt(x0) + dt(kt) + wx[0]
        out[1] = dt(x1) + wx[1]
        out[2] = dt(x2) + dt(kdm) + wx[2]
    else:
        out[0] = dt(kt) + wx[0]
        out[1] = wx[1]
        out[2] = dt(kdm) + wx[2]
    return np.isfinite(out[0] + out[1] + out[2])


@njit
def rhonn_record(x0, x1, x2, W, mu, be, dw, kt, kdm, inc, phi, wx, out, rec_phi, rec_chi):
    """rhonn_predict, then, if out is finite, rec_phi ← phi and rec_chi ← out (the record
    the next EKF observe learns from; reference: ``RhonnModel.record``). Returns the
    finiteness of out (False: nothing recorded)."""
    if not rhonn_predict(x0, x1, x2, W, mu, be, dw, kt, kdm, inc, phi, wx, out):
        return False
    for k in range(phi.shape[0]):
        rec_phi[k] = phi[k]
    for r in range(rec_chi.shape[0]):
        rec_chi[r] = out[r]
    return True


@njit
def bilinear_coefficients(W, mono, tfac, a, d, w4, coef):
    """coef (3, 4) = W4 t with W4[i, mono_k, tfac_k] = W[i, k] and t = [1, a, d, a d]
    (reference: ``RhonnModel.bilinear_coefficients``, same summation order); float64."""
    t = (1.0, a, d, a * d)
    for r in range(3):
        for k in range(W.shape[1]):
            w4[r, mono[k], tfac[k]] = W[r, k]
        for m in range(4):
            coef[r, m] = ((w4[r, m, 0] * t[0] + w4[r, m, 1] * t[1]) + w4[r, m, 2] * t[2]
                          + w4[r, m, 3] * t[3])
