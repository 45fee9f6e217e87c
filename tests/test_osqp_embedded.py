"""OSQP's generated C solver (controller.core.mpc.osqp_embedded) against the Python osqp
extension: recorded QPs of closed-loop runs, separate workspaces per instance, the
fallback without a compiler, a call from numba nopython code, the whole closed loop."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs, PredictionContext, QpStatus
from controller.core.kernels import AVAILABLE
from controller.core.mpc import osqp_embedded
from controller.core.mpc.qp import LinearizedMpc, QpConfig
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from harness.bench.controller_step import _Plant, bench_inputs
from tests.helpers_proc import live_children
from tests.test_kernels import config_file

HAVE_CC = shutil.which("cc") is not None or shutil.which("gcc") is not None
needs_cc = pytest.mark.skipif(not HAVE_CC, reason="no C compiler")
needs_numba = pytest.mark.skipif(not AVAILABLE, reason="numba not importable")
CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc")


def closed_loop(name: str, cfg: str, steps: int, record: bool = False
                ) -> tuple[Any, np.ndarray, np.ndarray, list[tuple[np.ndarray, ...]]]:
    """Closed-loop run on the bench plant (μ 0.35, 65 km/h, DLC-like steering, seeded
    sensor noise). Returns (controller, torques (steps, 4) N·m, QP iterations (steps,),
    recorded QP rounds: (q, P_x, l, u, bounds changed) before each OSQP round)."""
    ctrl = make_controller(name, cfg)
    rounds: list[tuple[np.ndarray, ...]] = []
    if record:
        qp = ctrl.qp
        inner = qp._osqp_round

        def recording(ext: Any) -> Any:
            rounds.append((qp._q64.copy(), qp._px64.copy(), qp.l.copy(), qp.u.copy(),
                           np.array(qp._bounds_dirty)))
            return inner(ext)

        qp._osqp_round = recording
    p = load_vehicle_params()
    plant = _Plant(p, 0.35, 65 / 3.6)
    rng = np.random.default_rng(5)
    inp = ControllerInputs()
    torques = np.zeros((steps, 4))
    iters = np.zeros(steps, dtype=int)
    for k in range(steps):
        swa = bench_inputs(inp, plant, k * ctrl.ts, rng)
        out = ctrl.step(inp)
        torques[k] = out.torques
        iters[k] = out.qp_iterations
        plant.step(out.torques, swa / p.steering_ratio, ctrl.ts)
    return ctrl, torques, iters, rounds


def replay(qp: LinearizedMpc, rounds: list[tuple[np.ndarray, ...]]
           ) -> tuple[np.ndarray, list[QpStatus], np.ndarray]:
    """Feed recorded rounds through ``qp._osqp_round`` on its own solver (warm starts
    chained as in the run). Returns iterations, statuses and x (rounds, N)."""
    ext = qp.solver._solver
    its, sts, xs = [], [], []
    for q, px, lo, hi, dirty in rounds:
        qp._q64[:] = q
        qp._px64[:] = px
        qp.l[:] = lo
        qp.u[:] = hi
        qp._bounds_dirty = bool(dirty)
        it, st = qp._osqp_round(ext)
        its.append(it)
        sts.append(st)
        xs.append(np.array(ext.solution.x, dtype=float))
    return np.array(its), sts, np.array(xs)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list]:
    """QP rounds of a 400-step closed loop of each MPC controller on the Python osqp path."""
    tmp = tmp_path_factory.mktemp("rec")
    cfg = config_file(tmp, 'qp_backend = "osqp"')
    return {name: closed_loop(name, cfg, 400, record=True)[3] for name in CONTROLLERS}


@needs_cc
@pytest.mark.parametrize("name", CONTROLLERS)
def test_generated_solver_equals_the_extension_on_recorded_qps(
        name: str, recorded: dict[str, list], tmp_path: Path) -> None:
    """Same iterations and status every round, x within 1e-9 (measured: bit-identical)."""
    rounds = recorded[name]
    assert len(rounds) >= 400
    ref = make_controller(name, config_file(tmp_path, 'qp_backend = "osqp"')).qp
    emb = make_controller(name, config_file(tmp_path, 'qp_backend = "embedded"')).qp
    assert ref.backend == "osqp" and emb.backend == "embedded"
    it_r, st_r, x_r = replay(ref, rounds)
    it_e, st_e, x_e = replay(emb, rounds)
    assert st_r == st_e and np.array_equal(it_r, it_e)
    assert np.abs(x_r - x_e).max() <= 1e-9
    assert it_r.sum() > 5 * len(rounds)        # real work was compared, not warm no-ops
    assert QpStatus.SOLVED in st_r


@needs_cc
def test_two_instances_in_one_process_keep_their_own_workspace(
        recorded: dict[str, list], tmp_path: Path) -> None:
    """Interleaving two generated solvers gives each the answers it gives alone."""
    cfg = config_file(tmp_path, 'qp_backend = "embedded"')
    a, b, alone = (make_controller("nmpc-rhonn", cfg).qp for _ in range(3))
    assert a.solver.round_address() != b.solver.round_address()
    ra, rb = recorded["nmpc-rhonn"], recorded["lmpc"]
    xa, xb = [], []
    for k in range(200):
        xa.append(replay(a, ra[k:k + 1])[2][0])
        xb.append(replay(b, rb[k:k + 1])[2][0])
    _, _, x_alone = replay(alone, ra[:200])
    assert np.array_equal(np.array(xa), x_alone)
    assert not np.array_equal(np.array(xa), np.array(xb))


class _LinModel:
    """x⁺ = A x + B ΔM (nx = 3), enough for a LinearizedMpc."""

    nx = 3

    def __init__(self) -> None:
        self.A = np.array([[1.0, 0.0, 0.0], [0.0, 0.9, -0.8], [0.0, 0.05, 0.85]])
        self.B = np.array([0.0, 0.0, 3.3e-5])

    def predict(self, x, delta_m, ctx, out):
        out[:] = self.A @ x + self.B * delta_m

    def linearize(self, x, delta_m, ctx, a_out, b_out):
        a_out[:] = self.A
        b_out[:] = self.B


def test_without_a_compiler_auto_falls_back_to_python_osqp(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """$CC pointing at a missing binary (or RHONN_NO_CC=1): "auto" uses the Python path and
    says why once; "embedded" refuses; the answers are the Python path's."""
    monkeypatch.setenv("CC", "/nonexistent/bin/cc")
    monkeypatch.setattr(osqp_embedded, "_warned", set())
    with caplog.at_level(logging.WARNING, logger=osqp_embedded.__name__):
        mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "auto"}), ts=0.05)
        LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "auto"}), ts=0.05)
    assert mpc.backend == "osqp"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "/nonexistent/bin/cc" in lines[0]
    with pytest.raises(RuntimeError, match="no C compiler"):
        LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "embedded"}), ts=0.05)
    args = (np.array([18.0, 0.5, 0.3]), PredictionContext(), -0.5, 0.05, -500.0, 500.0, 0.0)
    dm, status, _, fb = mpc.solve(*args)
    ref = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "osqp"}), ts=0.05)
    assert (dm, status) == ref.solve(*args)[:2] and not fb
    monkeypatch.delenv("CC")
    monkeypatch.setenv("RHONN_NO_CC", "1")
    mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "auto"}), ts=0.05)
    assert mpc.backend == "osqp"


@needs_cc
def test_a_failed_build_falls_back(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A compiler that exists but fails (here: /bin/false) → Python path under "auto"."""
    monkeypatch.setenv("CC", "/bin/false")
    monkeypatch.setenv("RHONN_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(osqp_embedded, "_cc_version", {"/bin/false": "none"})
    monkeypatch.setattr(osqp_embedded, "_built", {})
    mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "auto"}), ts=0.05)
    assert mpc.backend == "osqp"
    assert not list((tmp_path / "osqp").glob("*.so"))


@needs_cc
def test_an_unwritable_cache_falls_back(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A cache dir that cannot be created (under a regular file) → Python path."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("RHONN_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.setattr(osqp_embedded, "_built", {})
    mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "auto"}), ts=0.05)
    assert mpc.backend == "osqp"


@needs_cc
def test_the_cache_is_keyed_and_reused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """One library per problem in the cache dir; a second build (memo cleared) reuses it;
    another problem (other settings) gets another file."""
    monkeypatch.setenv("RHONN_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(osqp_embedded, "_built", {})
    LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "embedded"}), ts=0.05)
    libs = sorted((tmp_path / "osqp").glob("*.so"))
    assert len(libs) == 1
    stamp = libs[0].stat().st_mtime_ns
    monkeypatch.setattr(osqp_embedded, "_built", {})
    LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": "embedded"}), ts=0.05)
    assert sorted((tmp_path / "osqp").glob("*.so")) == libs
    assert libs[0].stat().st_mtime_ns == stamp
    LinearizedMpc(_LinModel(), QpConfig.from_dict(
        {"qp_backend": "embedded", "osqp": {"max_iter": 150}}), ts=0.05)
    assert len(list((tmp_path / "osqp").glob("*.so"))) == 2
    assert not list((tmp_path / "osqp").glob(".*"))   # no temporary left behind


@needs_cc
@needs_numba
def test_the_generated_solver_is_callable_from_numba_nopython_code(
        recorded: dict[str, list], tmp_path: Path) -> None:
    """A @njit function writes the QP data into the bound buffers, calls the solver through
    its first-class function object and clips the iterate (pre-QP → solve → post in one
    compiled call); the same as the Python round on another instance."""
    from numba import njit

    @njit(cache=False)
    def one_call(solve, q_src, px_src, q, px, x, lo, hi, flags):
        q[:] = q_src                  # "pre-QP": the data into the bound buffers
        px[:] = px_src
        r = solve(flags)              # update + solve in C
        for i in range(x.size):       # "post": clip the iterate to the box
            x[i] = min(max(x[i], lo[i]), hi[i])
        return r // 64, r % 64

    cfg = config_file(tmp_path, 'qp_backend = "embedded"')
    jit_qp, py_qp = (make_controller("nmpc-rhonn", cfg).qp for _ in range(2))
    emb = jit_qp.solver
    wap = emb.round_wap()
    x_out = emb.solution.x
    rounds = recorded["nmpc-rhonn"][:100]
    it_py, st_py, x_py = replay(py_qp, rounds)
    for k, (q, px, lo, hi, dirty) in enumerate(rounds):
        jit_qp.l[:] = lo
        jit_qp.u[:] = hi
        it, st = one_call(wap, q, px, jit_qp._q64, jit_qp._px64, x_out, lo[:3], hi[:3],
                          np.int32(1 if dirty else 0))
        assert it == it_py[k] and st in (1, 2, 7)
        np.testing.assert_array_equal(x_out, np.clip(x_py[k], lo[:3], hi[:3]))
    assert st_py[-1] in (QpStatus.SOLVED, QpStatus.SOLVED_INACCURATE, QpStatus.MAX_ITER)


@needs_cc
def test_closed_loop_nmpc_rhonn_on_the_generated_solver_equals_the_python_path(
        tmp_path: Path) -> None:
    """Whole steps (400, every output torque) on both back ends: within 1e-9 N·m, same
    iterations (measured: bit-identical); also through the numpy reference path."""
    for kernels in ("numba", "numpy"):
        base = f'kernels = "{kernels}"\n'
        c_ref, t_ref, i_ref, _ = closed_loop(
            "nmpc-rhonn", config_file(tmp_path, base + 'qp_backend = "osqp"'), 400)
        c_emb, t_emb, i_emb, _ = closed_loop(
            "nmpc-rhonn", config_file(tmp_path, base + 'qp_backend = "embedded"'), 400)
        assert c_ref.qp.backend == "osqp" and c_emb.qp.backend == "embedded"
        assert np.abs(t_ref - t_emb).max() <= 1e-9
        assert np.array_equal(i_ref, i_emb) and i_ref.sum() > 1000
        assert np.abs(t_ref).max() > 100.0     # the loop really used ΔM


@needs_cc
def test_state_round_trip_and_reset_on_the_generated_solver(tmp_path: Path) -> None:
    """get_state/set_state (warm start x, y) and reset() behave as on the Python path."""
    out = {}
    for backend in ("osqp", "embedded"):
        mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({"qp_backend": backend}), ts=0.05)
        ctx = PredictionContext(ts=0.05)
        res = []
        for k in range(20):
            x0 = np.array([18.0, 0.2 * np.sin(0.3 * k), 0.1 * np.cos(0.2 * k)])
            res.append(mpc.solve(x0, ctx, 0.2 * np.sin(0.1 * k), 0.0, -1800.0, 1800.0, 0.0)[:3])
            if k == 9:
                state = mpc.get_state()
                mpc.reset()
                mpc.set_state(state)
        out[backend] = res
    assert out["osqp"] == out["embedded"]


TIMING_KEYS = ("wall_time_s", "step_us_p50", "step_us_p99", "turnaround_us_p50",
               "turnaround_us_p99", "period_jitter_us_p99", "bus_log_time_base", "bus_hub",
               "controller_summary", "plant_summary")


@needs_cc
def test_cross_process_dlc_gives_the_same_kpis_on_both_back_ends(tmp_path: Path) -> None:
    """`rhonn-harness run dlc-paper --controller nmpc-rhonn` (plant and controller as OS
    processes on the bus): default config ("auto" → the generated solver) and the same with
    $CC pointing at a missing compiler ("auto" → the Python path, clean fallback in the
    controller process): same KPIs, the same plant truth trace byte for byte."""
    exe = Path(sys.executable).parent / "rhonn-harness"
    runs = {}
    for label, cc in (("embedded", None), ("fallback", "/nonexistent/bin/cc")):
        env = dict(os.environ)
        env.pop("RHONN_NO_CC", None)
        if cc is None:
            env.pop("CC", None)
        else:
            env["CC"] = cc
        out = tmp_path / label
        res = subprocess.run([str(exe), "run", "dlc-paper", "--controller", "nmpc-rhonn",
                              "--duration", "6", "--out", str(out), "--no-plots", "--no-rrd"],
                             env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        runs[label] = json.loads((out / "metrics.json").read_text())
        runs[label]["truth"] = (out / "truth.csv").read_bytes()
    emb, fb = runs["embedded"], runs["fallback"]
    assert emb["controller_summary"]["qp_backend"] == "embedded"
    assert fb["controller_summary"]["qp_backend"] == "osqp"
    assert "not used" in (tmp_path / "fallback" / "controller.log").read_text()
    assert emb["completed"] is True and emb["max_abs_dM_Nm"] > 0.0
    assert {k: v for k, v in emb.items() if k not in TIMING_KEYS} == {
        k: v for k, v in fb.items() if k not in TIMING_KEYS}
    assert not live_children()


_BUILD_ONE = """
import sys
import numpy as np
from controller.core.mpc.qp import LinearizedMpc, QpConfig
sys.path.insert(0, {tests!r})
from test_osqp_embedded import _LinModel
mpc = LinearizedMpc(_LinModel(), QpConfig.from_dict({{"qp_backend": "embedded"}}), ts=0.05)
print(mpc.backend)
"""


@needs_cc
def test_parallel_processes_building_into_one_cache_do_not_collide(tmp_path: Path) -> None:
    """Three processes start with an empty cache at once: all get the generated solver,
    one library is left, no temporary file."""
    env = dict(os.environ, RHONN_CACHE_DIR=str(tmp_path))
    env.pop("CC", None)
    env.pop("RHONN_NO_CC", None)
    code = _BUILD_ONE.format(tests=str(Path(__file__).parent))
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(3)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], [e[-500:] for _, e in outs]
    assert [o.strip() for o, _ in outs] == ["embedded"] * 3
    assert len(list((tmp_path / "osqp").glob("*.so"))) == 1
    assert not list((tmp_path / "osqp").glob(".*"))
