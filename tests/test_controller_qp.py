"""The OSQP-based linearised MPC vs an independently built QP (finite differences of the
prediction, dense least squares) solved by active-set enumeration and scipy's BVLS."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from controller.core.interfaces import PredictionContext, QpStatus
from controller.core.mpc.qp import LinearizedMpc, QpConfig


class LinearModel:
    """x⁺ = A x + B ΔM + c (nx = 3), a PredictionModel with exact Jacobians."""

    nx = 3

    def __init__(self, rng: np.random.Generator) -> None:
        self.A = np.zeros((3, 3))
        self.A[0, 0] = 0.99                             # vx nearly constant
        self.A[1:, 1:] = 0.9 * np.eye(2) + 0.05 * rng.normal(size=(2, 2))  # stable lateral
        self.B = np.array([0.0, 1e-5 * rng.normal(), 3.3e-5 * (1 + 0.3 * rng.random())])
        self.c = np.array([0.0, 0.02 * rng.normal(), 0.01 * rng.normal()])

    def initial_state(self, inputs, out):  # pragma: no cover - unused here
        out[:] = 0.0

    def predict(self, x, delta_m, ctx, out):
        out[:] = self.A @ x + self.B * delta_m + self.c

    def linearize(self, x, delta_m, ctx, a_out, b_out):
        a_out[:] = self.A
        b_out[:] = self.B


class NanModel(LinearModel):
    def predict(self, x, delta_m, ctx, out):
        out[:] = np.nan


def brute_force(P: np.ndarray, q: np.ndarray, C: np.ndarray, lo: np.ndarray,
                hi: np.ndarray) -> np.ndarray:
    """min ½ zᵀPz + qᵀz s.t. lo ≤ C z ≤ hi by enumerating every active set (each row at its
    lower bound, upper bound or inactive) and solving the equality-constrained KKT system."""
    n, m = P.shape[0], C.shape[0]
    best, best_f = None, np.inf
    for choice in itertools.product((0, 1, 2), repeat=m):
        rows = [i for i in range(m) if choice[i]]
        if len(rows) > n:
            continue
        Ca = C[rows]
        b = np.array([lo[i] if choice[i] == 1 else hi[i] for i in rows])
        if not np.all(np.isfinite(b)):
            continue
        K = np.block([[P, Ca.T], [Ca, np.zeros((len(rows), len(rows)))]])
        try:
            sol = np.linalg.solve(K, np.concatenate([-q, b]))
        except np.linalg.LinAlgError:
            continue
        z = sol[:n]
        if np.all(C @ z >= lo - 1e-9) and np.all(C @ z <= hi + 1e-9):
            f = 0.5 * z @ P @ z + q @ z
            if f < best_f - 1e-12:
                best, best_f = z, f
    assert best is not None
    return best


def _setup(rng: np.random.Generator, rate: float = 0.0, n: int = 3,
           unconstrained_first: bool = True) -> LinearizedMpc:
    cfg = QpConfig.from_dict({"horizon": n, "rate_limit_nm_per_s": rate,
                              "unconstrained_first": unconstrained_first,
                              "osqp": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iter": 4000}})
    return LinearizedMpc(LinearModel(rng), cfg, ts=0.05)


def outputs(model: LinearModel, x0: np.ndarray, u_nm: np.ndarray,
            ctx: PredictionContext) -> np.ndarray:
    """The prediction's outputs [ωr_1 rad/s, β_1 rad, ωr_2, β_2, …] for ΔM u_nm (N·m),
    by plain simulation of the model (β = Vy/Vx)."""
    x, out = x0.copy(), []
    for ui in u_nm:
        nxt = np.zeros(3)
        model.predict(x, float(ui), ctx, nxt)
        out += [nxt[2], nxt[1] / nxt[0]]
        x = nxt
    return np.array(out)


def reference_qp(model: LinearModel, cfg: QpConfig, x0: np.ndarray, ctx: PredictionContext,
                 z_bar: np.ndarray, r_ref: float, b_ref: float) -> tuple[np.ndarray, np.ndarray]:
    """The paper's eq. 22 cost, linearised at z̄, built without the implementation: the
    output Jacobian by central finite differences of the simulated prediction, then the dense
    least-squares form ‖M z − b‖² with M = [W½ G; √λ I], b = [W½ (y_d − ȳ + G z̄); 0]
    (W = diag(q, r, q, r, …), z in u_scale units). Returns (P, q) of ½ zᵀPz + qᵀz."""
    us, n = cfg.u_scale, len(z_bar)
    y_bar = outputs(model, x0, z_bar * us, ctx)
    G = np.empty((2 * n, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1e-3
        G[:, j] = (outputs(model, x0, (z_bar + e) * us, ctx)
                   - outputs(model, x0, (z_bar - e) * us, ctx)) / 2e-3
    w_sqrt = np.sqrt(np.ravel(np.column_stack([cfg.q_yaw, cfg.r_beta])))
    y_d = np.tile([r_ref, b_ref], n)
    M = np.vstack([w_sqrt[:, None] * G, math.sqrt(cfg.input_reg) * np.eye(n)])
    b = np.concatenate([w_sqrt * (y_d - y_bar + G @ z_bar), np.zeros(n)])
    return 2.0 * M.T @ M, -2.0 * M.T @ b


@pytest.mark.parametrize("unconstrained_first", [True, False])
@pytest.mark.parametrize("rate", [0.0, 20_000.0])
def test_osqp_matches_an_independently_built_qp_solved_exhaustively(
        rate: float, unconstrained_first: bool) -> None:
    """P, q, the box and the rate rows are rebuilt from the model and the settings alone
    (never read from the implementation), solved by active-set enumeration and, for the
    box-only case, also by scipy's bounded least squares; the answer must match, whether
    OSQP solved every QP or the unconstrained minimiser took those where no row binds
    (exactly those: counted)."""
    rng = np.random.default_rng(11)
    ctx = PredictionContext(ts=0.05)
    n_active = 0
    for trial in range(25):
        mpc = _setup(rng, rate, unconstrained_first=unconstrained_first)
        cfg, n, us = mpc.cfg, mpc.N, mpc.cfg.u_scale
        x0 = np.array([rng.uniform(8, 30), rng.normal(0, 0.5), rng.normal(0, 0.2)])
        cap = rng.uniform(300.0, 1800.0)
        prev = rng.uniform(-cap, cap)
        sol0 = rng.uniform(-cap, cap, n)
        mpc.sol[:] = sol0
        spread = 1.0 if trial % 2 else 0.03    # far references → constrained optimum
        r_ref = x0[2] + rng.normal(0, 0.3 * spread)
        b_ref = x0[1] / x0[0] + rng.normal(0, 0.05 * spread)
        dm, status, _, fb = mpc.solve(x0, ctx, r_ref, b_ref, -cap, cap, prev)
        assert status in (QpStatus.SOLVED, QpStatus.SOLVED_INACCURATE) and not fb
        # The reference problem: linearised at the previous solution shifted by one stage.
        z_bar = np.append(sol0[1:], sol0[-1]) / us
        P_ref, q_ref = reference_qp(mpc.model, cfg, x0, ctx, z_bar, r_ref, b_ref)
        C = np.eye(n)
        lo, hi = np.full(n, -cap / us), np.full(n, cap / us)
        if rate:
            d = rate * 0.05 / us
            C = np.vstack([C, np.eye(n) - np.eye(n, k=-1)])
            lo = np.concatenate([lo, [prev / us - d], np.full(n - 1, -d)])
            hi = np.concatenate([hi, [prev / us + d], np.full(n - 1, d)])
        z_ref = brute_force(P_ref, q_ref, C, lo, hi)
        z = mpc.sol / us
        np.testing.assert_allclose(z, z_ref, atol=2e-4, err_msg=f"trial {trial}")
        if not rate:
            M = np.linalg.cholesky(P_ref / 2.0).T             # ½zᵀPz + qᵀz = ‖Mz − c‖² + k
            c = np.linalg.solve(M.T, -q_ref / 2.0)
            z_lsq = lsq_linear(M, c, bounds=(lo, hi), method="bvls", tol=1e-12).x
            np.testing.assert_allclose(z, z_lsq, atol=2e-4, err_msg=f"trial {trial}")
        active = bool(np.any(np.abs(C @ z_ref - lo) < 1e-9) or
                      np.any(np.abs(C @ z_ref - hi) < 1e-9))
        n_active += active
        assert mpc.unconstrained_solves == (unconstrained_first and not active)
        # Never outside the box (N·m), rate rows within OSQP tolerance.
        assert np.all(mpc.sol >= -cap - 1e-9) and np.all(mpc.sol <= cap + 1e-9)
        assert dm == mpc.sol[0]
        if rate:
            d = C @ z
            assert np.all(d >= lo - 1e-5) and np.all(d <= hi + 1e-5)
    assert 3 <= n_active <= 22          # both constrained and unconstrained optima occur


def test_condensed_prediction_matrix_matches_finite_differences() -> None:
    """G = ∂[ωr_i, β_i]/∂z from the sensitivities equals a numerical derivative."""
    rng = np.random.default_rng(4)
    mpc = _setup(rng)
    ctx = PredictionContext(ts=0.05)
    x0 = np.array([15.0, 0.3, 0.1])
    mpc.ubar[:] = [100.0, -200.0, 50.0]
    mpc._linearise(x0, ctx)
    G = mpc.G.copy()

    def outputs(u: np.ndarray) -> np.ndarray:
        x, out = x0.copy(), []
        for ui in u:
            nxt = np.zeros(3)
            mpc.model.predict(x, ui, ctx, nxt)
            out += [nxt[2], nxt[1] / nxt[0]]
            x = nxt
        return np.array(out)

    u0 = mpc.ubar.copy()
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        num = (outputs(u0 + e) - outputs(u0 - e)) / 2.0 * mpc.cfg.u_scale
        np.testing.assert_allclose(G[:, j], num, rtol=1e-5, atol=1e-9)


def test_warm_start_lowers_iterations() -> None:
    rng = np.random.default_rng(2)
    model = LinearModel(rng)
    ctx = PredictionContext(ts=0.05)
    totals = {}
    for warm in (True, False):
        cfg = QpConfig.from_dict({"unconstrained_first": False,
                                  "osqp": {"warm_starting": warm}})
        mpc = LinearizedMpc(model, cfg, ts=0.05)
        total = 0
        for k in range(300):   # slowly varying references: a DLC-like sweep
            x0 = np.array([18.0, 0.2 * np.sin(0.05 * k), 0.1 * np.sin(0.05 * k + 0.5)])
            _, st, it, _ = mpc.solve(x0, ctx, 0.25 * np.sin(0.05 * k + 1.0), 0.0,
                                     -1800.0, 1800.0, 0.0)
            assert st == QpStatus.SOLVED
            total += it
        totals[warm] = total
    assert totals[True] < 0.8 * totals[False], totals


def test_solver_failure_uses_the_flagged_decayed_fallback() -> None:
    rng = np.random.default_rng(0)
    mpc = LinearizedMpc(NanModel(rng), QpConfig(), ts=0.05)
    dm, status, _, fb = mpc.solve(np.array([18.0, 0.0, 0.0]), PredictionContext(), 0.1,
                                  0.0, -1800.0, 1800.0, 600.0)
    assert fb and status == QpStatus.FALLBACK
    assert dm == pytest.approx(0.5 * 600.0)


def test_max_iter_is_reported_and_the_iterate_is_kept_in_the_box() -> None:
    rng = np.random.default_rng(9)
    cfg = QpConfig.from_dict({"osqp": {"max_iter": 1, "check_termination": 1,
                                       "warm_starting": False}})
    mpc = LinearizedMpc(LinearModel(rng), cfg, ts=0.05)
    dm, status, iters, fb = mpc.solve(np.array([18.0, 0.5, 0.3]), PredictionContext(),
                                      -0.5, 0.05, -500.0, 500.0, 0.0)
    assert status == QpStatus.MAX_ITER and not fb and iters == 1
    assert -500.0 <= dm <= 500.0


def test_sqp_iterations_on_a_linear_model_do_not_change_the_answer() -> None:
    rng = np.random.default_rng(6)
    model = LinearModel(rng)
    ctx = PredictionContext(ts=0.05)
    out = []
    for k in (1, 3):
        cfg = QpConfig.from_dict({"sqp_iterations": k,
                                  "osqp": {"eps_abs": 1e-9, "eps_rel": 1e-9}})
        mpc = LinearizedMpc(model, cfg, ts=0.05)
        out.append(mpc.solve(np.array([18.0, 0.1, 0.05]), ctx, 0.2, -0.01,
                             -1800.0, 1800.0, 0.0)[0])
    assert out[0] == pytest.approx(out[1], abs=0.5)   # N·m
