"""Scenario files, course geometry, friction field and path projection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plant_sim.params import load_vehicle_params
from plant_sim.path import ReferencePath, curvature_path
from plant_sim.road import friction_from_spec
from plant_sim.scenario import list_scenarios, load_scenario
from plant_sim.simulation import Simulation, run_passive

CANONICAL = ["dlc-paper", "dlc-paper-high-mu", "iso3888-2", "slippery-curve", "sine-with-dwell",
             "step-steer", "constant-radius", "split-mu-braking"]
B = load_vehicle_params().vehicle_width_m


def test_canonical_scenarios_exist() -> None:
    names = list_scenarios()
    for name in CANONICAL:
        assert name in names


@pytest.mark.parametrize("name", list_scenarios())
def test_every_scenario_runs(name: str) -> None:
    sc = load_scenario(name)
    assert sc.duration_s > 0 and sc.initial_speed_mps > 0
    for line in sc.boundaries:
        assert line.ndim == 2 and line.shape[1] == 2
    assert sc.cones.ndim == 2 and sc.cones.shape[1] == 2
    tr = run_passive(sc, max_time_s=1.5)
    for col, values in tr.items():
        assert np.all(np.isfinite(values)), col
    assert tr["t_s"][-1] == pytest.approx(1.5)


def test_iso3888_1_geometry() -> None:
    sc = load_scenario("dlc-paper")
    assert sc.mu == 0.35 and sc.speed_kmh == pytest.approx(65.0)
    l1, l3, l5 = sc.lanes
    assert (l1.x0, l1.x1, l3.x0, l3.x1, l5.x0, l5.x1) == (0.0, 15.0, 45.0, 70.0, 95.0, 110.0)
    assert l1.y_left - l1.y_right == pytest.approx(1.1 * B + 0.25)
    assert l3.y_left - l3.y_right == pytest.approx(1.2 * B + 0.25)
    assert l5.y_left - l5.y_right == pytest.approx(1.3 * B + 0.25)
    assert l3.y_right - l1.y_right == pytest.approx(3.5)
    assert l5.y_right == pytest.approx(l1.y_right)
    # the reference path runs through the lane centres
    for lane in sc.lanes:
        xm = 0.5 * (lane.x0 + lane.x1)
        i = int(np.argmin(np.abs(sc.path.x - xm)))
        assert sc.path.y[i] == pytest.approx(0.5 * (lane.y_left + lane.y_right), abs=1e-6)
    assert sc.driver.speed == "coast"


def test_iso3888_2_geometry() -> None:
    sc = load_scenario("iso3888-2")
    l1, l3, l5 = sc.lanes
    assert (l1.x0, l1.x1, l3.x0, l3.x1, l5.x0, l5.x1) == (0.0, 12.0, 25.5, 36.5, 49.0, 61.0)
    assert l1.y_left - l1.y_right == pytest.approx(1.1 * B + 0.25)
    assert l3.y_left - l3.y_right == pytest.approx(B + 1.0)
    assert l5.y_left - l5.y_right == pytest.approx(max(1.3 * B + 0.25, 3.0))
    assert l3.y_right - l1.y_left == pytest.approx(1.0)


def test_overrides_and_errors() -> None:
    sc = load_scenario("sine-with-dwell", mu=0.5, speed_kmh=70.0, amplitude_deg=123.0,
                       direction="right")
    assert sc.mu == 0.5 and sc.speed_kmh == pytest.approx(70.0)
    assert sc.driver.amplitude_deg == 123.0 and sc.driver.direction == "right"
    split = load_scenario("split-mu-braking", mu=0.5)
    assert split.friction.mu_at(10.0, 1.0) == pytest.approx(0.5)
    assert split.friction.mu_at(10.0, -1.0) == pytest.approx(0.1)
    with pytest.raises(KeyError):
        load_scenario("dlc-paper", no_such_parameter=1.0)
    with pytest.raises(KeyError):
        load_scenario("no-such-scenario")
    with pytest.raises(ValueError):
        load_scenario("sine-with-dwell", direction="up")


def test_slippery_curve_enables_stabilisation_after_5s() -> None:
    sc = load_scenario("slippery-curve")
    assert sc.stab_enable_after_s == 5.0 and sc.mu == 0.35
    sim = Simulation(sc)
    assert not sim.sensors().stab_enable
    while sim.time_s < 4.99:
        sim.step_comm(None)
    assert not sim.sensors().stab_enable
    sim.step_comm(None)
    assert sim.sensors().stab_enable
    # the driver holds 85 km/h
    while sim.time_s < 3.0 + 5.0:
        sim.step_comm(None)
    assert sim.vehicle.vx * 3.6 == pytest.approx(85.0, abs=1.5)


def test_split_mu_field_under_the_wheels() -> None:
    tr = run_passive(load_scenario("split-mu-braking"), max_time_s=2.0)
    assert tr["mu_fl"][-1] == pytest.approx(1.0) and tr["mu_rl"][-1] == pytest.approx(1.0)
    assert tr["mu_fr"][-1] == pytest.approx(0.2) and tr["mu_rr"][-1] == pytest.approx(0.2)
    field = friction_from_spec({"mu": 0.8, "patches": [{"x0": 0, "x1": 10, "mu": 0.3}]})
    assert field.mu_at(5.0, 100.0) == 0.3 and field.mu_at(-1.0, 0.0) == 0.8
    assert field.uniform is None and friction_from_spec({"mu": 0.6}).uniform == 0.6


def test_split_mu_braking_stops_the_car() -> None:
    tr = run_passive(load_scenario("split-mu-braking"))
    assert tr["speed_mps"][-1] < 0.5
    assert np.max(np.abs(tr["lateral_dev_m"])) < 1.0
    assert tr["spun"][-1] == 0.0


def test_path_projection_sign_and_arc_length() -> None:
    path = ReferencePath(np.array([0.0, 10.0, 20.0]), np.array([0.0, 0.0, 0.0]))
    s, lat = path.project(5.0, 1.0)
    assert s == pytest.approx(5.0) and lat == pytest.approx(1.0)  # + = left
    s, lat = path.project(6.0, -2.0)
    assert s == pytest.approx(6.0) and lat == pytest.approx(-2.0)
    circle = curvature_path([(2 * math.pi * 50.0, 1 / 50.0, 1 / 50.0)], ds=0.25)
    # a point inside a left circle is to the left of the path
    circle.reset()
    _, lat = circle.project(0.0, 10.0)
    assert lat == pytest.approx(10.0, abs=0.05)
