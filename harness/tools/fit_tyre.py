"""Fit the controller's simplified pure-slip MF (controller/core/model/tyre.py) to the plant's tyre.

The paper's NMPC-MF / 7-DoF-MF take their MF parameters from CarSim; we take ours from the
plant: sample ``plant_sim.tyre.make_vehicle_tyres()`` at pure longitudinal (α = 0) and pure
lateral (κ = 0) slip over a grid of loads at μ scaling 1 (the nominal road), and fit per axle
and direction (C, d1, d2, k1, k2, k3, e1, e2) with scipy least squares. Residuals are
normalised by Fz (a friction-coefficient error) so light and heavy loads weigh alike.
The plant's rolling-resistance and aero-drag coefficients are copied into [resistance].

Usage: ``python -m harness.tools.fit_tyre [--out controller/config/mf_tyre_fit.toml]``
(without --out the TOML is printed). Deterministic: fixed grid, fixed start values.
"""

from __future__ import annotations

import argparse
import datetime
import math
import sys
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from controller.core.model.tyre import MfCurve, mf_force
from plant_sim.params import load_vehicle_params as load_plant_params
from plant_sim.tyre import MagicFormulaTyre, make_vehicle_tyres

FIT_LOADS_N = np.linspace(1000.0, 9000.0, 17)
"""Normal loads of the fit grid, N (static ≈ 5000 N; covers the load transfer at ~1 g)."""
FIT_ALPHA_RAD = 0.6 * np.linspace(-1.0, 1.0, 81) ** 2 * np.sign(np.linspace(-1.0, 1.0, 81))
"""Slip angles, rad: ±0.6 rad, quadratically spaced (dense in the linear range)."""
FIT_KAPPA = 0.6 * np.linspace(-1.0, 1.0, 81) ** 2 * np.sign(np.linspace(-1.0, 1.0, 81))
"""Longitudinal slips, -: ±0.6, quadratically spaced."""

PARAM_NAMES = ("c", "d1", "d2", "k1", "k2", "k3", "e1", "e2")


def sample_plant(tyre: MagicFormulaTyre, direction: str, loads: np.ndarray,
                 slips: np.ndarray) -> np.ndarray:
    """Plant pure-slip force in the controller's 'positive curve' convention, N.

    direction "lateral": F = −Fy(κ = 0, α) (ISO: +α gives −Fy); "longitudinal": F = Fx(κ, 0).
    Returns an array (len(loads), len(slips)).
    """
    out = np.empty((loads.size, slips.size))
    for i, fz in enumerate(loads):
        for j, s in enumerate(slips):
            if direction == "lateral":
                out[i, j] = -tyre.forces(0.0, float(s), float(fz))[1]
            else:
                out[i, j] = tyre.forces(float(s), 0.0, float(fz))[0]
    return out


def model_forces(curve: MfCurve, loads: np.ndarray, slips: np.ndarray) -> np.ndarray:
    """The controller's MF on the same grid, N (μ = 1)."""
    out = np.empty((loads.size, slips.size))
    for i, fz in enumerate(loads):
        for j, s in enumerate(slips):
            out[i, j] = mf_force(curve, float(s), float(fz), 1.0)
    return out


def _vectorised(p: np.ndarray, fz0: float, fz: np.ndarray, s: np.ndarray) -> np.ndarray:
    c, d1, d2, k1, k2, k3, e1, e2 = p
    dfz = (fz - fz0) / fz0
    K = fz * (k1 + k2 * dfz) * np.exp(k3 * dfz)
    D = fz * (d1 + d2 * dfz)
    E = np.minimum(e1 + e2 * dfz, 1.0)
    B = K / (c * D)
    u = B * s
    return D * np.sin(c * np.arctan(u - E * (u - np.arctan(u))))


@dataclass(frozen=True, slots=True)
class FitResult:
    """One fitted curve with its residuals (N, and % of the local peak force)."""

    curve: MfCurve
    rms_n: float
    max_n: float
    rms_pct_peak: float
    stiffness_err_pct: float  # slip stiffness at Fz0 vs the plant's, %


def fit_curve(tyre: MagicFormulaTyre, direction: str) -> FitResult:
    """Least-squares fit of one axle/direction to the plant tyre."""
    slips = FIT_ALPHA_RAD if direction == "lateral" else FIT_KAPPA
    target = sample_plant(tyre, direction, FIT_LOADS_N, slips)
    fz_grid = np.repeat(FIT_LOADS_N[:, None], slips.size, axis=1)
    s_grid = np.repeat(slips[None, :], FIT_LOADS_N.size, axis=0)
    fz0 = float(tyre.fz0)
    k0 = 15.0 if direction == "lateral" else 20.0
    c0 = 1.3 if direction == "lateral" else 1.6
    x0 = np.array([c0, 1.0, 0.0, k0, 0.0, 0.0, 0.0, 0.0])
    lower = [1.0, 0.1, -1.0, 1.0, -20.0, -3.0, -5.0, -5.0]
    upper = [2.0, 3.0, 1.0, 80.0, 20.0, 3.0, 1.0, 5.0]

    def residual(p: np.ndarray) -> np.ndarray:
        return ((_vectorised(p, fz0, fz_grid, s_grid) - target) / fz_grid).ravel()

    sol = least_squares(residual, x0, bounds=(lower, upper), x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=5000)
    curve = MfCurve(fz0_n=fz0, **{k: float(v) for k, v in zip(PARAM_NAMES, sol.x, strict=True)})
    err = model_forces(curve, FIT_LOADS_N, slips) - target
    peak = np.abs(target).max(axis=1, keepdims=True)
    plant_k = (-tyre.cornering_stiffness(fz0) if direction == "lateral"
               else tyre.slip_stiffness(fz0))
    return FitResult(
        curve=curve,
        rms_n=float(np.sqrt(np.mean(err**2))),
        max_n=float(np.abs(err).max()),
        rms_pct_peak=float(100.0 * np.sqrt(np.mean((err / peak) ** 2))),
        stiffness_err_pct=float(100.0 * (curve.stiffness(fz0) / plant_k - 1.0)),
    )


def fit_all() -> dict[str, dict[str, FitResult]]:
    """Fits for {"front", "rear"} × {"lateral", "longitudinal"}."""
    front, rear = make_vehicle_tyres()
    return {axle: {d: fit_curve(t, d) for d in ("lateral", "longitudinal")}
            for axle, t in (("front", front), ("rear", rear))}


def render_toml(fits: dict[str, dict[str, FitResult]], command: str) -> str:
    """The mf_tyre_fit.toml text, with residuals and provenance as comments."""
    lines = [
        "# Simplified pure-slip Magic Formula for the controller's 7-DoF models",
        "# (controller/core/model/tyre.py). FITTED to the plant's tyre (plant_sim/tyre.py,",
        "# make_vehicle_tyres(), mu scaling 1, pure slip) by harness/tools/fit_tyre.py.",
        f"# Generated {datetime.date.today().isoformat()} by: {command}",
        f"# Grid: Fz {FIT_LOADS_N[0]:.0f}..{FIT_LOADS_N[-1]:.0f} N ({FIT_LOADS_N.size} loads), "
        f"|alpha| <= {FIT_ALPHA_RAD.max():.2f} rad, |kappa| <= {FIT_KAPPA.max():.2f} "
        f"({FIT_ALPHA_RAD.size} slips each).",
        "# Residuals (model - plant): RMS and max in N, RMS in % of the local peak force,",
        "# and the slip-stiffness error at Fz0:",
    ]
    for axle, per in fits.items():
        for d, f in per.items():
            lines.append(f"#   {axle:5s} {d:12s} rms {f.rms_n:7.1f} N  max {f.max_n:7.1f} N  "
                         f"rms {f.rms_pct_peak:5.2f} % of peak  "
                         f"K(Fz0) {f.stiffness_err_pct:+.2f} %")
    pp = load_plant_params()
    lines += [
        "",
        "[model]",
        "mu_nominal = 1.0   # friction scaling of the nominal (dry) road; the controller "
        "does not know mu",
        "",
        "[resistance]",
        "# Driving resistances of the 7-DoF models, copied from the plant's parameters",
        "# (plant_sim/params/vehicle.toml), as the paper took its model parameters from CarSim.",
        f"rolling_coeff = {pp.rolling_resistance_coeff!r}   # -, force f*m*g",
        f"drag_n_per_mps2 = {0.5 * pp.air_density_kgpm3 * pp.drag_area_m2!r}   "
        "# N/(m/s)^2, k = rho*Cd*A/2",
        f"ramp_speed_mps = {pp.rr_smoothing_speed_mps!r}   # m/s, rolling resistance ramp-in",
    ]
    for axle, per in fits.items():
        for d, f in per.items():
            lines += ["", f"[{axle}.{d}]"]
            for fld in fields(MfCurve):
                val = getattr(f.curve, fld.name)
                lines.append(f"{fld.name} = {val!r}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Fit and print or write the TOML; print the residual table to stderr."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="TOML file to write")
    args = ap.parse_args(argv)
    fits = fit_all()
    cmd = "python -m harness.tools.fit_tyre" + (f" --out {args.out}" if args.out else "")
    text = render_toml(fits, cmd)
    for axle, per in fits.items():
        for d, f in per.items():
            print(f"{axle:5s} {d:12s} rms {f.rms_n:7.1f} N  max {f.max_n:7.1f} N  "
                  f"{f.rms_pct_peak:5.2f} % of peak  K(Fz0) {f.stiffness_err_pct:+.2f} %",
                  file=sys.stderr)
    if args.out is None:
        sys.stdout.write(text)
    else:
        args.out.write_text(text)
    if not all(math.isfinite(f.rms_n) for per in fits.values() for f in per.values()):
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
