"""Compiled EKF weight updates (reference: ``controller.core.learning.ekf``).

``ekf_update``: the standard form, the same operations as ``BatchedEkf.update`` + its
guards except the periodic eigenvalue floor (left to the caller, which counts it).
``ud_update``: the UD form of ``UdEkf.update`` (Bierman measurement update, rank-one
time update).
Both work in the dtype of their arrays (float64 or float32): scalar arguments (Python
floats) are cast to it on entry, so no operation is promoted. Return codes: 0 updated, 1 rejected.
``flags`` (int64, 2): [trace resets, weight clips] added by this call.
"""

from __future__ import annotations

import numpy as np

from controller.core.kernels import njit


@njit
def _clip_weights(W, wm, flags):
    """|W| ≤ wm element-wise; flags[1] counts the updates that had to clip (both EKF forms)."""
    clipped = False
    for i in range(W.shape[0]):
        for a in range(W.shape[1]):
            if W[i, a] > wm:
                W[i, a] = wm
                clipped = True
            elif W[i, a] < -wm:
                W[i, a] = -wm
                clipped = True
    if clipped:
        flags[1] += 1


@njit
def _all_finite(h, e):
    """True when every entry of the regressor h (L,) and the error e (n,) is finite (one
    sum each: a NaN or ±inf makes the sum non-finite)."""
    sh = h.dtype.type(0.0)
    for j in range(h.shape[0]):
        sh += h[j]
    se = e.dtype.type(0.0)
    for i in range(e.shape[0]):
        se += e[i]
    return np.isfinite(sh) and np.isfinite(se)


@njit
def ekf_update(P, W, h, e, R, zeta, q, p_floor, trace_max, p0, w_max, ph, s, flags):
    """Standard EKF step for n neurons sharing the regressor h (L,): see BatchedEkf.update.

    P (n, L, L), W (n, L), e (n,), R (n,), zeta (n,); ph (n, L) and s (n,) scratch."""
    n, L = W.shape
    dt = W.dtype.type
    zero = dt(0.0)
    qv, pf, tm, p0v, wm = dt(q), dt(p_floor), dt(trace_max), dt(p0), dt(w_max)
    if not _all_finite(h, e):
        return 1
    ssum = zero
    smin = np.inf
    for i in range(n):
        acc_s = zero
        for a in range(L):
            acc = zero
            for b in range(L):
                acc += P[i, a, b] * h[b]
            ph[i, a] = acc
        for a in range(L):
            acc_s += ph[i, a] * h[a]
        s[i] = acc_s + R[i]
        ssum += s[i]
        smin = min(smin, s[i])
    if not (np.isfinite(ssum) and smin > zero):
        return 1
    for i in range(n):
        ze = zeta[i] * e[i]
        for a in range(L):
            W[i, a] += (ph[i, a] / s[i]) * ze
        rs = np.sqrt(s[i])
        for a in range(L):
            ph[i, a] = ph[i, a] / rs
        for a in range(L):
            ua = ph[i, a]
            for b in range(L):
                P[i, a, b] -= ua * ph[i, b]
        for a in range(L):
            P[i, a, a] += qv
    # Guards: diagonal floor, trace bound (reset to p0·I), weight bound.
    for i in range(n):
        tr = zero
        for a in range(L):
            if P[i, a, a] < pf:
                P[i, a, a] = pf
            tr += P[i, a, a]
        if tr > tm:
            for a in range(L):
                for b in range(L):
                    P[i, a, b] = zero
                P[i, a, a] = p0v
            flags[0] += 1
    _clip_weights(W, wm, flags)
    return 0


@njit
def ud_update(U, D, W, h, e, R, zeta, q, d_floor, trace_max, p0, w_max, k, f, flags):
    """Bierman measurement update + rank-one (Agee–Turner) time update P ← P + q·I of
    P_i = U_i D_i U_iᵀ.

    U (n, L, L) unit upper triangular, D (n, L) > 0; k, f (L,) scratch. Same guards as
    the standard form, on D (floor d_floor) and on trace(P)."""
    n, L = W.shape
    dt = W.dtype.type
    zero = dt(0.0)
    one = dt(1.0)
    qv, df, tm, p0v, wm = dt(q), dt(d_floor), dt(trace_max), dt(p0), dt(w_max)
    if not _all_finite(h, e):
        return 1
    # Innovation variances first: reject before touching any state.
    for i in range(n):
        s = R[i]
        for j in range(L):
            fj = zero
            for a in range(j + 1):
                fj += U[i, a, j] * h[a]
            s += D[i, j] * fj * fj
        if not (np.isfinite(s) and s > zero):
            return 1
    for i in range(n):
        # ---- Bierman: f = Uᵀh, v = D f, sequential scalar update of U, D and gain k.
        for j in range(L):
            fj = zero
            for a in range(j + 1):
                fj += U[i, a, j] * h[a]
            f[j] = fj
        alpha = R[i]
        for j in range(L):
            vj = D[i, j] * f[j]
            beta = alpha
            alpha = alpha + f[j] * vj
            lam = -f[j] / beta
            D[i, j] = D[i, j] * (beta / alpha)
            for a in range(j):
                tmp = U[i, a, j]
                U[i, a, j] = tmp + lam * k[a]
                k[a] = k[a] + vj * tmp
            k[j] = vj
        ze = zeta[i] * e[i]
        for a in range(L):
            W[i, a] += (k[a] / alpha) * ze
        # ---- Time update P ← P + q I as L rank-one updates P + q e_k e_kᵀ (Agee–Turner);
        #      for a unit vector e_k only columns ≤ k change: ≈ L³/6 multiply-adds.
        for kk in range(L):
            for a in range(L):
                f[a] = zero
            f[kk] = one
            c = qv
            for j in range(kk, -1, -1):
                p = f[j]
                dj = D[i, j]
                dn = dj + c * p * p
                bet = c * p / dn
                c = c * dj / dn
                D[i, j] = dn
                for a in range(j):
                    f[a] = f[a] - p * U[i, a, j]
                    U[i, a, j] = U[i, a, j] + bet * f[a]
    # Guards: D floor, trace bound (reset to U = I, D = p0), weight bound.
    for i in range(n):
        tr = zero
        for j in range(L):
            if D[i, j] < df:
                D[i, j] = df
            col = zero
            for a in range(j + 1):
                col += U[i, a, j] * U[i, a, j]
            tr += D[i, j] * col
        if tr > tm:
            for a in range(L):
                for b in range(L):
                    U[i, a, b] = zero
                U[i, a, a] = one
                D[i, a] = p0v
            flags[0] += 1
    _clip_weights(W, wm, flags)
    return 0


@njit
def ekf_observe(P, W, h, x, chi, e, R, zeta, q, p_floor, trace_max, p0, w_max, ph, s,
                flags):
    """e = x − χ (n,) (x measured state, χ recorded prediction; e in W's dtype), flags
    zeroed, then ekf_update: the observe step of the RHONN in one call (reference:
    ``RhonnModel.observe`` → ``BatchedEkf.update``). Returns 1 rejected, 0 updated with
    both flags 0, 2 updated with a flag set (the caller reads flags only then)."""
    flags[0] = 0
    flags[1] = 0
    for i in range(e.shape[0]):
        e[i] = x[i] - chi[i]
    if ekf_update(P, W, h, e, R, zeta, q, p_floor, trace_max, p0, w_max, ph, s, flags):
        return 1
    return 2 if (flags[0] != 0 or flags[1] != 0) else 0


@njit
def ud_observe(U, D, W, h, x, chi, e, R, zeta, q, d_floor, trace_max, p0, w_max, k, f,
               flags):
    """ekf_observe for the UD form: e = x − χ, flags zeroed, then ud_update (reference:
    ``RhonnModel.observe`` → ``UdEkf.update``). Returns 1 rejected, 0 updated with both
    flags 0, 2 updated with a flag set."""
    flags[0] = 0
    flags[1] = 0
    for i in range(e.shape[0]):
        e[i] = x[i] - chi[i]
    if ud_update(U, D, W, h, e, R, zeta, q, d_floor, trace_max, p0, w_max, k, f, flags):
        return 1
    return 2 if (flags[0] != 0 or flags[1] != 0) else 0
