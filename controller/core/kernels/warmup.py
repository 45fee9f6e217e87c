"""Compile (or load from numba's cache) every kernel before a controller steps.

Called by the controller factory, so ``rhonn-controller`` prints "ready" only after
this; a first compile takes seconds, a cache load tens of milliseconds per kernel.
"""

from __future__ import annotations

import numpy as np

from controller.core.kernels import AVAILABLE

_done: set[tuple[str, str]] = set()
PARTS = ("qp", "allocation", "rhonn", "ekf-standard", "ekf-ud", "baselines")


def warm_up(dtype: type = np.float64, parts: tuple[str, ...] = PARTS) -> None:
    """Call the kernels of ``parts`` once on small finite data of ``dtype`` (results
    discarded). Only what a controller uses is compiled: a cold compile costs seconds
    per kernel (measured ≈ 20 s for all float64 kernels on the loaded 2-core machine)."""
    if not AVAILABLE:
        return
    key = np.dtype(dtype).name
    todo = [p for p in parts if (key, p) not in _done]
    if not todo:
        return
    from controller.core.kernels import allocation, baselines, ekf, mpc

    dt = dtype
    n, L, N = 3, 15, 3
    W = np.zeros((n, L), dt)
    h = np.full(L, 0.1, dt)
    e = np.zeros(n, dt)
    R = np.ones(n, dt)
    fl = np.zeros(2, np.int64)
    sc = (1e-5, 1e-9, 1e4, 1.0, 100.0)
    one = 1.0
    ub = np.zeros(N, dt)
    xbar = np.zeros((N + 1, 3), dt)
    A = np.zeros((N, 3, 3), dt)
    B = np.zeros((N, 3), dt)
    if "ekf-standard" in todo:
        P = np.tile(np.eye(L, dtype=dt), (n, 1, 1))
        ekf.ekf_update(P, W, h, e, R, R, *sc, np.zeros((n, L), dt), np.zeros(n, dt), fl)
        ekf.ekf_observe(P, W, h, np.zeros(3), np.zeros(3, dt), e, R, R, *sc,
                        np.zeros((n, L), dt), np.zeros(n, dt), fl)
    if "ekf-ud" in todo:
        U = np.tile(np.eye(L, dtype=dt), (n, 1, 1))
        ekf.ud_update(U, np.ones((n, L), dt), W, h, e, R, R, *sc, np.zeros(L, dt),
                      np.zeros(L, dt), fl)
        ekf.ud_observe(U, np.ones((n, L), dt), W, h, np.zeros(3), np.zeros(3, dt), e, R, R,
                       *sc, np.zeros(L, dt), np.zeros(L, dt), fl)
    if "rhonn" in todo:
        x0 = np.array([18.0, 0.0, 0.0], dt)
        deriv = np.zeros((3, L), np.intp)
        mpc.rhonn_rollout_jac(x0, ub, W, np.ones(4, dt), np.ones(4, dt), one, one, one, one,
                              one, True, deriv, np.zeros(L + 2, dt), np.zeros(3, dt),
                              np.zeros(3, dt), xbar, A, B)
        for inc in (True, False):
            mpc.rhonn_predict(18.0, 0.0, 0.0, W, np.ones(4, dt), np.ones(4, dt), 0.0, 0.0,
                              0.0, inc, np.zeros(L, dt), np.zeros(3, dt), np.zeros(3))
            mpc.rhonn_record(18.0, 0.0, 0.0, W, np.ones(4, dt), np.ones(4, dt), 0.0, 0.0,
                             0.0, inc, np.zeros(L, dt), np.zeros(3, dt), np.zeros(3),
                             np.zeros(L, dt), np.zeros(3, dt))
        mono = np.zeros(L, np.intp)
        mpc.bilinear_coefficients(W, mono, mono, 0.5, 0.5, np.zeros((3, 4, 4)),
                                  np.zeros((3, 4)))
        from controller.core.kernels.references import algorithm1_search, demand_blend

        a1 = (np.ones(4), np.array([5.0, 1e-4, 0.3, 0.05, 1.0, 0.15, 3, 3, 1]),
              np.linspace(-1.0, 1.0, 9))
        algorithm1_search(np.zeros((3, 4)), *a1, 0.0, 0.0, 1.0, -0.1, 0.1, np.zeros(5),
                          np.zeros(36))
        demand_blend(18.0, 0.0, 0.0, 0.01, 1.0, 0.0, 0.0, 0.0, np.ones(28), W, mono, mono,
                     np.zeros((3, 4, 4)), np.zeros((3, 4)), a1[1], a1[0], a1[2],
                     np.zeros(36), np.zeros(5), np.zeros(11))
    if "rhonn" in todo or "baselines" in todo:   # the fused pre-QP step of each model
        from controller.core.kernels import fused

        shapes = ((N + 1) * 3, N, N * 9, N * 3, N * 3 * N, 2 * N * N, 2 * N, 2 * N, 2 * N,
                  N * N, N * (N + 1) // 2, N, N, 3)
        off = np.concatenate(([0], np.cumsum(shapes))).astype(np.intp)
        buf = np.zeros(int(off[-1]), dt)
        tri = np.triu_indices(N)
        qa = (buf, off, N, 3, tri[0].astype(np.intp), tri[1].astype(np.intp),
              np.zeros(len(tri[0])), np.zeros(N), np.array([18.0, 0.0, 0.0]), -1.0, 1.0, 0.0,
              0.0, 3.0, 1000.0, 0.2, 1e12)
        if "rhonn" in todo:
            fused.pre_qp_rhonn(*qa, W, np.ones(4, dt), np.ones(4, dt), one, one, one, one,
                               one, True, np.zeros((3, L), np.intp), np.zeros(L + 2, dt),
                               np.zeros(3, dt), np.zeros(3, dt))
        if "baselines" in todo:
            fused.pre_qp_heun(*qa, 0, np.ones(10), np.ones((4, 18)), 0.0, 0.0, 0.05, 0.05,
                              100.0, 0.5, 200, 1.0, np.zeros(128))
    if "qp" in todo:
        yd = np.zeros(2 * N, dt)
        mpc.warm_start(ub, ub.copy(), one, one, yd, one, one)
        tri = np.triu_indices(N)
        mpc.condense_build(xbar, A, B, np.zeros(3, dt), True, one, one, np.ones(2 * N, dt),
                           one, yd, ub, tri[0].astype(np.intp), tri[1].astype(np.intp),
                           np.zeros((N, 3, N), dt), np.zeros((2 * N, N), dt),
                           np.zeros(2 * N, dt), np.zeros((N, N), dt),
                           np.zeros(len(tri[0]), dt), np.zeros(N, dt), 1e12)
        mpc.accept(np.zeros(N), ub, ub, one, ub.copy(), ub.copy())
        mpc.accept_sol(np.zeros(N), ub, ub, one, ub.copy(), ub.copy(), ub.copy())
    if "baselines" in todo:
        # the MPC's rollout in dtype; the one-step prediction's scratch is float64
        for u, xb, a, b in ((ub, xbar, A, B), (np.zeros(1), np.zeros((2, 3)),
                                                np.zeros((1, 3, 3)), np.zeros((1, 3)))):
            baselines.heun_rollout_jac(0, np.array([18.0, 0.0, 0.0]), u, np.ones(10),
                                       np.ones((4, 18)), 0.0, 0.0, 0.05, 0.05, 100.0, 0.5,
                                       200, 1.0, xb, a, b, np.zeros(128))
    if "allocation" in todo:
        prm = np.ones(13, dt)
        for lc in (False, True):   # wheel speeds arrive as float64 in both precisions
            allocation.allocate(one, one, one, one, np.ones(4), np.ones(4, dt), lc, prm,
                                np.zeros(4, dt))
        allocation.motor_limits(np.ones(4), prm, np.ones(4, dt))
        allocation.dm_capacity(np.ones(4), prm, np.ones(4, dt))
    _done.update((key, p) for p in todo)
