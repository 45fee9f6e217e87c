"""The compiled plant kernel gives the same truth trace as the pure-Python model, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim import kernel, path_kernel
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation, run_passive

pytestmark = pytest.mark.skipif(not kernel.enabled(), reason="numba not available")


def _trace(monkeypatch: pytest.MonkeyPatch, mode: str, scenario: str,
           max_time_s: float) -> dict[str, np.ndarray]:
    monkeypatch.setenv("RHONN_PLANT_KERNEL", mode)
    return run_passive(load_scenario(scenario), seed=3, max_time_s=max_time_s)


@pytest.mark.parametrize(("scenario", "seconds"), [("dlc-paper", 6.0), ("step-steer", 4.0),
                                                   ("sine-with-dwell", 6.0)])
def test_kernel_trace_is_bit_identical_to_python(monkeypatch: pytest.MonkeyPatch,
                                                 scenario: str, seconds: float) -> None:
    py = _trace(monkeypatch, "python", scenario, seconds)
    nb = _trace(monkeypatch, "numba", scenario, seconds)
    assert py.keys() == nb.keys() and py["t_s"].size > 100
    for column in py:
        a, b = np.asarray(py[column], dtype=np.float64), np.asarray(nb[column], dtype=np.float64)
        assert np.array_equal(a.view(np.uint64), b.view(np.uint64)), column


def test_kernel_is_used_and_commands_reach_it(monkeypatch: pytest.MonkeyPatch) -> None:
    rows = {}
    for mode, command in (("python", True), ("numba", True), ("numba", False)):
        monkeypatch.setenv("RHONN_PLANT_KERNEL", mode)
        sim = Simulation(load_scenario("step-steer"), seed=1)
        assert sim.vehicle.use_kernel is (mode == "numba")
        for k in range(150):  # a yaw moment command every other cycle
            sim.step_comm([300.0, -300.0, 300.0, -300.0] if command and k % 2 else None)
        rows[(mode, command)] = sim.truth_row()
    assert rows[("python", True)] == rows[("numba", True)]
    # the command reached the kernel's wheels: the car yaws differently without it
    assert rows[("numba", True)]["yaw_rate_radps"] != rows[("numba", False)]["yaw_rate_radps"]


@pytest.mark.skipif(path_kernel.project_compiled is None, reason="numba not installed")
def test_compiled_path_projection_is_bit_identical_to_python() -> None:
    """Points around every scenario's path, warm-started near and far from their segment,
    before the start and past the end: the compiled projection equals the Python loop."""
    rng = np.random.default_rng(7)
    for name in ("dlc-paper", "constant-radius", "sine-with-dwell", "step-steer"):
        path = load_scenario(name).path
        n = len(path.x)
        for _ in range(200):
            k = int(rng.integers(0, n))
            px = float(path.x[k] + rng.normal(0.0, 4.0))
            py = float(path.y[k] + rng.normal(0.0, 4.0))
            hint = int(np.clip(k + rng.integers(-30, 30), 0, n - 2))
            cols = (path._x, path._y, path._s, path._hx, path._hy)
            assert path_kernel.project_compiled(px, py, *path._arrays, hint) == \
                path_kernel.project_window(px, py, *cols, hint)
        for px, py in ((path.x[0] - 20.0, path.y[0]), (path.x[-1] + 20.0, path.y[-1])):
            for hint in (0, n - 2):
                assert path_kernel.project_compiled(float(px), float(py), *path._arrays,
                                                    hint) == \
                    path_kernel.project_window(float(px), float(py), path._x, path._y,
                                               path._s, path._hx, path._hy, hint)
