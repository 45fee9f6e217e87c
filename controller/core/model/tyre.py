"""The controller's own simplified tyre models (the controller never imports plant_sim).

Sign conventions (ISO 8855, same as the plant):

* slip angle α = atan2(v_y,wheel, |v_x,wheel|), rad; a positive α gives a NEGATIVE side
  force, i.e. Fy = C·α with the paper's negative cornering stiffness C (Table 1: Cf, Cr < 0).
  Here the MF is written with a positive curve: Fy = −F(α), F odd and increasing near 0.
* longitudinal slip κ = (ω·R − v_x,wheel) / |v_x,wheel|, dimensionless; Fx = +F(κ).

Pure-slip Magic Formula (Pacejka's simplified form, one curve per axle and direction)::

    dfz = (Fz − Fz0) / Fz0
    D   = μ · Fz · (d1 + d2·dfz)                 peak force, N
    K   = Fz · (k1 + k2·dfz) · exp(k3·dfz)      slip stiffness B·C·D, N/rad or N/(unit slip)
    E   = min(e1 + e2·dfz, 1)                    curvature, -
    B   = K / (C·D)                              stiffness factor, 1/rad or 1/(unit slip)
    F   = D · sin(C · atan(B·s − E·(B·s − atan(B·s))))

μ is the friction scaling factor (1 = the nominal road the parameters describe). The
functions below are scalar and pure-Python on purpose: for four wheels this is several times
faster than numpy on 4-element arrays and allocates nothing but transient floats.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

FZ_MIN_N = 50.0
"""Normal-load floor, N: a lifted wheel keeps a tiny load so B = K/(C·D) stays finite."""

FZ_CAP_FACTOR = 2.0
"""The load used in the formulas is capped at FZ_CAP_FACTOR·Fz0 (the fit covers ≤ 1.8·Fz0;
beyond it the fitted K(Fz) polynomial is extrapolation and eventually turns negative)."""


@dataclass(frozen=True, slots=True)
class MfCurve:
    """One pure-slip MF curve (one axle, one direction). Units as in the module docstring.

    fz0_n: normalising load Fz0, N. c: shape factor C, -. d1, d2: peak friction coefficient
    and its load sensitivity, -. k1, k2, k3: slip-stiffness coefficients, (N/unit)/N, -, -.
    e1, e2: curvature and its load sensitivity, -.
    """

    fz0_n: float
    c: float
    d1: float
    d2: float
    k1: float
    k2: float
    k3: float
    e1: float
    e2: float

    def stiffness(self, fz_n: float) -> float:
        """Slip stiffness K = B·C·D at load fz_n N, N per unit slip (N/rad for α)."""
        dfz = (fz_n - self.fz0_n) / self.fz0_n
        return fz_n * (self.k1 + self.k2 * dfz) * math.exp(self.k3 * dfz)

    def fz_cap(self) -> float:
        """Largest load the formulas are evaluated at, N (callers clamp to it)."""
        return FZ_CAP_FACTOR * self.fz0_n

    def peak(self, fz_n: float, mu: float) -> float:
        """Peak force D at load fz_n N and friction scaling mu, N."""
        dfz = (fz_n - self.fz0_n) / self.fz0_n
        return mu * fz_n * (self.d1 + self.d2 * dfz)


@dataclass(frozen=True, slots=True)
class MfAxle:
    """Lateral and longitudinal curves of the tyres of one axle."""

    lateral: MfCurve
    longitudinal: MfCurve


@dataclass(frozen=True, slots=True)
class Resistance:
    """Driving resistances of the 7-DoF models (taken from the plant by harness/tools/fit_tyre.py,
    as the paper took its model parameters from CarSim; zero = none).

    rolling_coeff: rolling-resistance coefficient f, force f·m·g against the motion, -.
    drag_n_per_mps2: aerodynamic k = ½·ρ·Cd·A, force k·vx·|vx|, N/(m/s)².
    ramp_speed_mps: the rolling resistance ramps in linearly below this speed, m/s.
    """

    rolling_coeff: float = 0.0
    drag_n_per_mps2: float = 0.0
    ramp_speed_mps: float = 0.5


@dataclass(frozen=True, slots=True)
class MfTyreSet:
    """Front and rear axle tyre curves, the nominal friction scaling the controller uses and
    the driving resistances (see Resistance).

    mu_nominal: friction scaling, -. The road μ is not on the bus, so by default the MF model
    runs at the value of the road its parameters describe: the plant's tyre at its own peak
    (scaling factor 1 = dry road). The paper's NMPC-MF does the same with the CarSim tyre
    data; on the μ = 0.35 road this model therefore over-predicts grip — the model mismatch
    the baseline is meant to show. A controller told the road μ (``[controller]
    mu_estimate`` > 0, see with_mu_estimate) runs at that value instead.
    """

    front: MfAxle
    rear: MfAxle
    mu_nominal: float = 1.0
    resistance: Resistance = Resistance()


def mf_eval(curve: MfCurve, s: float, fz_n: float, mu: float) -> tuple[float, float, float]:
    """Pure-slip MF force and its partial derivatives.

    s: slip (α rad, or κ -). fz_n: normal load, N (callers clamp it to ≥ FZ_MIN_N).
    mu: friction scaling, -.
    Returns (F N, ∂F/∂s N/unit, ∂F/∂Fz N/N).
    """
    fz0 = curve.fz0_n
    dfz = (fz_n - fz0) / fz0
    ex = math.exp(curve.k3 * dfz)
    kpoly = curve.k1 + curve.k2 * dfz
    K = fz_n * kpoly * ex
    dK = ex * (kpoly + fz_n * (curve.k2 + kpoly * curve.k3) / fz0)
    dpoly = curve.d1 + curve.d2 * dfz
    D = mu * fz_n * dpoly
    dD = mu * (dpoly + fz_n * curve.d2 / fz0)
    E = curve.e1 + curve.e2 * dfz
    dE = curve.e2 / fz0
    if E > 1.0:  # MF requires E <= 1 (else the curve folds back)
        E = 1.0
        dE = 0.0
    C = curve.c
    if D <= 1e-9 or K <= 0.0:  # no grip (mu = 0) or a non-physical fit at this load
        return 0.0, 0.0, 0.0
    B = K / (C * D)
    dB = (dK * D - K * dD) / (C * D * D)
    u = B * s
    atu = math.atan(u)
    phi = u - E * (u - atu)
    y = C * math.atan(phi)
    sy = math.sin(y)
    g = D * math.cos(y) * C / (1.0 + phi * phi)  # ∂F/∂phi
    dphi_du = (1.0 - E) + E / (1.0 + u * u)
    F = D * sy
    dF_ds = g * dphi_du * B
    dF_dfz = dD * sy + g * (dphi_du * s * dB - (u - atu) * dE)
    return F, dF_ds, dF_dfz


def mf_force(curve: MfCurve, s: float, fz_n: float, mu: float) -> float:
    """Pure-slip MF force F(s), N (no derivatives; see mf_eval for arguments)."""
    fz0 = curve.fz0_n
    dfz = (fz_n - fz0) / fz0
    K = fz_n * (curve.k1 + curve.k2 * dfz) * math.exp(curve.k3 * dfz)
    D = mu * fz_n * (curve.d1 + curve.d2 * dfz)
    E = min(curve.e1 + curve.e2 * dfz, 1.0)
    if D <= 1e-9 or K <= 0.0:
        return 0.0
    C = curve.c
    u = (K / (C * D)) * s
    return D * math.sin(C * math.atan(u - E * (u - math.atan(u))))


def with_mu_estimate(tyres: MfTyreSet, mu_estimate: float) -> MfTyreSet:
    """``tyres`` with mu_nominal replaced by the road friction the controller is told,
    ``mu_estimate`` (-); 0 = not told: ``tyres`` unchanged. The MF peak force scales with
    it (D = μ·Fz·(d1 + d2·dfz)); the slip stiffness K does not (same cornering stiffness, the
    curve saturates at a smaller slip). ValueError for a negative or non-finite value."""
    mu = float(mu_estimate)
    if not (math.isfinite(mu) and mu >= 0.0):
        raise ValueError(f"mu_estimate must be 0 (not told) or > 0, got {mu_estimate!r}")
    if mu == 0.0:
        return tyres
    return replace(tyres, mu_nominal=mu)


def _curve(table: dict[str, float]) -> MfCurve:
    keys = ("fz0_n", "c", "d1", "d2", "k1", "k2", "k3", "e1", "e2")
    return MfCurve(**{k: float(table[k]) for k in keys})


def load_mf_tyres(path: str | Path | None = None) -> MfTyreSet:
    """Read controller/config/mf_tyre_fit.toml (or `path`) into an MfTyreSet."""
    if path is None:
        text = resources.files("controller").joinpath("config/mf_tyre_fit.toml").read_text()
    else:
        text = Path(path).read_text()
    data = tomllib.loads(text)
    axles = []
    for name in ("front", "rear"):
        axle = data[name]
        axles.append(MfAxle(lateral=_curve(axle["lateral"]),
                            longitudinal=_curve(axle["longitudinal"])))
    res = data.get("resistance", {})
    return MfTyreSet(front=axles[0], rear=axles[1],
                     mu_nominal=float(data["model"]["mu_nominal"]),
                     resistance=Resistance(
                         rolling_coeff=float(res.get("rolling_coeff", 0.0)),
                         drag_n_per_mps2=float(res.get("drag_n_per_mps2", 0.0)),
                         ramp_speed_mps=float(res.get("ramp_speed_mps", 0.5))))
