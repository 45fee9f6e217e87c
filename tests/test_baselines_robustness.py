"""Robustness of the baseline models: no allocation in the hot path, no exceptions on bad
input (NaN/inf/zero speed), and the layering rule (controller never imports plant_sim)."""

from __future__ import annotations

import ast
import math
import pathlib
import tracemalloc

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from controller.core.interfaces import ControllerInputs, PredictionContext
from controller.core.model.baselines import ESTIMATOR_KINDS, MODEL_KINDS, make_estimator, make_model
from controller.core.params import load_vehicle_params
from tests.tracing import coverage_paused, other_threads_held

P = load_vehicle_params()
MODELS = {k: make_model(k, P) for k in MODEL_KINDS}
ANY = st.floats(allow_nan=True, allow_infinity=True)


@pytest.mark.parametrize("kind", MODEL_KINDS)
@pytest.mark.parametrize("vx", [18.0, 2.0])  # one and several sub-steps
@coverage_paused()
@other_threads_held()
def test_predict_and_linearize_do_not_allocate(kind: str, vx: float) -> None:
    """Over 100 calls (tracemalloc is slow): no memory growth (nothing cached or leaked) and
    a peak of at most a few transient Python floats/tuples (< 2.5 kB; no arrays): results go
    into the caller's arrays."""
    model = MODELS[kind]
    x, out = np.array([vx, 0.4, 0.2]), np.zeros(3)
    a, b = np.zeros((3, 3)), np.zeros(3)
    ctx = PredictionContext(delta_w=0.05, total_torque=100.0, ts=0.05)

    def calls() -> None:
        model.predict(x, 300.0, ctx, out)
        model.linearize(x, 300.0, ctx, a, b)
        model.predict_linearize(x, 300.0, ctx, out, a, b)

    for _ in range(20):
        calls()
    tracemalloc.start()
    try:
        for _ in range(20):
            calls()
        cur0, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(100):
            calls()
        cur1, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert cur1 - cur0 < 256
    assert peak - cur0 < 2500


@coverage_paused()
@other_threads_held()
def test_estimator_step_does_not_allocate() -> None:
    est = make_estimator("7dof-mf", P)
    est.initialise(20.0)
    inp, tq = ControllerInputs(swa_rad=0.5), np.full(4, 50.0)
    for _ in range(5):
        est.step(inp, tq, 0.01)
    tracemalloc.start()
    try:
        est.step(inp, tq, 0.01)
        cur0, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(200):
            res = est.step(inp, tq, 0.01)
        cur1, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert cur1 - cur0 < 256
    assert peak - cur0 < 2500
    assert res is est.step(inp, tq, 0.0)  # the same internal array every call


@given(vx=ANY, vy=ANY, r=ANY, dm=ANY, d=ANY, tt=ANY, ts=ANY)
def test_bad_inputs_never_raise(vx: float, vy: float, r: float, dm: float, d: float,
                                tt: float, ts: float) -> None:
    """Any input: no exception; outputs all finite, or all NaN (the documented guard)."""
    x = np.array([vx, vy, r])
    ctx = PredictionContext(delta_w=d, total_torque=tt, ts=ts)
    for model in MODELS.values():
        out, a, b = np.zeros(3), np.zeros((3, 3)), np.zeros(3)
        model.predict(x, dm, ctx, out)
        assert np.all(np.isfinite(out)) or np.all(np.isnan(out))
        model.predict_linearize(x, dm, ctx, out, a, b)
        res = np.concatenate([out, a.ravel(), b])
        assert np.all(np.isfinite(res)) or np.all(np.isnan(res))
        inputs_finite = all(math.isfinite(v) for v in (vx, vy, r, dm, d, tt, ts))
        if not inputs_finite or not 0.0 < ts <= 1.0:
            assert np.all(np.isnan(res))


@given(vx=st.floats(-100.0, 100.0), vy=st.floats(-50.0, 50.0), r=st.floats(-10.0, 10.0),
       dm=st.floats(-1e4, 1e4), d=st.floats(-1.0, 1.0), tt=st.floats(-5000.0, 5000.0),
       ts=st.floats(1e-4, 0.2))
def test_physical_range_gives_finite_outputs(vx: float, vy: float, r: float, dm: float,
                                             d: float, tt: float, ts: float) -> None:
    """Includes vx = 0 and reversing: the slip denominators and the sub-step rule keep it
    finite."""
    x = np.array([vx, vy, r])
    ctx = PredictionContext(delta_w=d, total_torque=tt, ts=ts)
    for model in MODELS.values():
        out, a, b = np.zeros(3), np.zeros((3, 3)), np.zeros(3)
        model.predict_linearize(x, dm, ctx, out, a, b)
        assert np.all(np.isfinite(out)) and np.all(np.isfinite(a)) and np.all(np.isfinite(b))


def test_zero_speed_standstill() -> None:
    for model in MODELS.values():
        out, a, b = np.zeros(3), np.zeros((3, 3)), np.zeros(3)
        model.predict_linearize(np.zeros(3), 0.0, PredictionContext(0.3, 0.0, 0.05), out, a, b)
        np.testing.assert_allclose(out, 0.0, atol=1e-12)  # steering at standstill: no motion


@pytest.mark.parametrize("kind", ESTIMATOR_KINDS)
@given(swa=ANY, t1=ANY, t2=ANY, dt=ANY, vx0=ANY)
def test_estimator_bad_inputs(kind: str, swa: float, t1: float, t2: float, dt: float,
                              vx0: float) -> None:
    """Non-finite steering/torques hold the last valid value, bad dt does not integrate,
    a non-finite initial state falls back to rest, a huge one is clamped: the estimate stays
    finite."""
    est = make_estimator(kind, P)
    inp = ControllerInputs(vx=vx0, swa_rad=swa)
    tq = np.array([t1, t2, t1, t2])
    for step_dt in (dt, 0.01, dt if math.isfinite(dt) and dt < 0.05 else 0.02):
        x = est.step(inp, tq, step_dt)
        assert np.all(np.isfinite(x))


def test_controller_never_imports_plant_sim() -> None:
    root = pathlib.Path(__file__).resolve().parents[1] / "controller"
    for path in root.rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [n.name for n in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            assert not any(n.split(".")[0] == "plant_sim" for n in names), path
