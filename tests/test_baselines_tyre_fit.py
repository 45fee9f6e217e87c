"""The controller's MF fit (controller/config/mf_tyre_fit.toml) against the plant's tyre.

The test imports plant_sim (tests and the harness may; the controller may not)."""

from __future__ import annotations

import math
import tomllib
from importlib import resources

import numpy as np
import pytest

from controller.core.model.chassis import make_corners
from controller.core.model.tyre import load_mf_tyres, mf_force
from controller.core.params import load_vehicle_params
from harness.tools.fit_tyre import PARAM_NAMES, fit_all
from plant_sim.params import load_vehicle_params as load_plant_params
from plant_sim.tyre import make_vehicle_tyres

P = load_vehicle_params()
TYRES = load_mf_tyres()
PLANT = dict(zip(("front", "rear"), make_vehicle_tyres(), strict=True))

# a grid that is NOT the fit grid: other loads, uniform slips
LOADS = np.array([1200.0, 2600.0, 4100.0, 4974.0, 5179.0, 6300.0, 7700.0, 8800.0])
SLIPS = np.linspace(-0.5, 0.5, 101)


@pytest.mark.parametrize("axle", ["front", "rear"])
@pytest.mark.parametrize("direction", ["lateral", "longitudinal"])
def test_fit_reproduces_plant_pure_slip(axle: str, direction: str) -> None:
    """Stated accuracy: RMS error ≤ 0.5 % of the local peak force, max ≤ 1.5 % of it."""
    curve = getattr(getattr(TYRES, axle), direction)
    tyre = PLANT[axle]
    err_rel = []
    for fz in LOADS:
        plant = np.array([-tyre.forces(0.0, s, fz)[1] if direction == "lateral"
                          else tyre.forces(s, 0.0, fz)[0] for s in SLIPS])
        model = np.array([mf_force(curve, float(s), float(fz), 1.0) for s in SLIPS])
        err_rel.append((model - plant) / np.abs(plant).max())
    e = np.array(err_rel)
    assert math.sqrt(float(np.mean(e**2))) < 0.005
    assert np.abs(e).max() < 0.015


def test_fitted_cornering_stiffness_matches_table1_at_static_load() -> None:
    """The plant's tyre is scaled to Table 1, so the fit must be too (within 0.5 %): this is
    what makes 7dof-mf and 7dof-li (Table 1 per wheel) agree in the linear range."""
    for c in make_corners(P):
        curve = (TYRES.front if c.front else TYRES.rear).lateral
        assert curve.stiffness(c.fz_static_n) == pytest.approx(c.c_lin, rel=0.005)


def test_fit_peak_friction_matches_plant() -> None:
    for axle in ("front", "rear"):
        for fz in (3000.0, 5080.0, 8000.0):
            mux, muy = PLANT[axle].peak_mu(fz)
            a = getattr(TYRES, axle)
            assert a.longitudinal.peak(fz, 1.0) / fz == pytest.approx(mux, rel=0.005)
            assert a.lateral.peak(fz, 1.0) / fz == pytest.approx(muy, rel=0.005)


def test_shipped_toml_is_the_current_fit() -> None:
    """Re-running `python -m harness.tools.fit_tyre` reproduces the shipped parameters (fails if the
    plant tyre changed and the TOML was not regenerated)."""
    shipped = tomllib.loads(
        resources.files("controller").joinpath("config/mf_tyre_fit.toml").read_text())
    assert shipped["model"]["mu_nominal"] == 1.0
    pp = load_plant_params()
    assert shipped["resistance"]["rolling_coeff"] == pp.rolling_resistance_coeff
    assert shipped["resistance"]["drag_n_per_mps2"] == pytest.approx(
        0.5 * pp.air_density_kgpm3 * pp.drag_area_m2)
    for axle, per in fit_all().items():
        for direction, fit in per.items():
            table = shipped[axle][direction]
            assert table["fz0_n"] == fit.curve.fz0_n
            for name in PARAM_NAMES:
                assert table[name] == pytest.approx(getattr(fit.curve, name), rel=1e-4,
                                                    abs=1e-5), (axle, direction, name)
            assert fit.rms_pct_peak < 0.5
