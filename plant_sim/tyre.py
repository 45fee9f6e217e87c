"""Magic Formula tyre (MF 5.2-style, Pacejka 2006) with combined slip, camber = 0.

Sign convention (ISO 8855 / TNO W-axis, the convention of the published coefficient set):

* wheel axes: x along the wheel heading (forward), y to the left, z up;
* slip ratio ``kappa = (omega * r - Vx) / |Vx|`` (-): > 0 when driving (Fx > 0), < 0 when braking;
* slip angle ``alpha = atan(Vsy / |Vx|)`` (rad), Vsy = lateral velocity of the contact point in
  wheel axes: > 0 when the contact point slides to the LEFT, which produces a NEGATIVE Fy.
  The cornering stiffness dFy/dalpha is therefore negative, the same sign as the paper's
  Cf = -108350 N/rad and Cr = -105898 N/rad (axle values);
* Fx, Fy in N in wheel axes (Fy > 0 to the left).

Equations: Pacejka, "Tyre and Vehicle Dynamics", 2nd ed. (2006), Sec. 4.3.2 (pure slip
4.E9-4.E30 without camber/turn slip) and combined slip 4.E50-4.E67 (cosine weighting
functions Gx_alpha, Gy_kappa). Parameters: Table A3.1 (see ``params/tyre.toml``).

Road friction enters through the scaling factors LMUX = mu_x and LMUY = mu_y.
The hot path is plain ``math`` on floats (numpy per-call overhead would dominate).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

_FZ_MIN_N = 1.0  # below 1 N the wheel is off the ground: no force (avoids 1/Dx overflow)
_MU_MIN = 1e-3  # floor on the friction scaling: keeps By = Ky/(Cy*Dy) finite
_FZ_MAX_FACTOR = 3.0  # load used in the formulas is capped at 3 x Fz0' (outside the fit)


def load_tyre_config(path: str | Path | None = None) -> dict[str, Any]:
    """Read the tyre TOML (default: the packaged ``plant_sim/params/tyre.toml``)."""
    if path is None:
        text = resources.files("plant_sim").joinpath("params/tyre.toml").read_text()
    else:
        text = Path(path).read_text()
    return tomllib.loads(text)


@dataclass(frozen=True, slots=True)
class TyreCoefficients:
    """The MF coefficients actually evaluated (published set, symmetrised, scaled).

    fz0_n: scaled nominal load FNOMIN*LFZO, N. r0_m: unloaded radius, m. qsy1: rolling
    resistance coefficient, -. sigma_alpha_m, sigma_kappa_m: relaxation lengths, m.
    v_low_mps: low-speed blend speed, m/s. Other fields are the dimensionless MF coefficients
    with the lambda scaling factors already multiplied in.
    """

    fz0_n: float
    r0_m: float
    pcx1: float
    pdx1: float
    pdx2: float
    pex1: float
    pex2: float
    pex3: float
    pex4: float
    pkx1: float
    pkx2: float
    pkx3: float
    phx1: float
    phx2: float
    rbx1: float
    rbx2: float
    rcx1: float
    rhx1: float
    pcy1: float
    pdy1: float
    pdy2: float
    pey1: float
    pey2: float
    pey3: float
    pky1: float
    pky2: float
    phy1: float
    phy2: float
    pvy1: float
    pvy2: float
    rby1: float
    rby2: float
    rby3: float
    rcy1: float
    rhy1: float
    rhy2: float
    rvy1: float
    rvy2: float
    rvy4: float
    rvy5: float
    rvy6: float
    qsy1: float
    sigma_alpha_m: float
    sigma_kappa_m: float
    v_low_mps: float


def build_coefficients(config: dict[str, Any], axle: str) -> TyreCoefficients:
    """Apply symmetrisation and the vehicle scaling of ``config`` for ``axle`` ('front'/'rear')."""
    if axle not in ("front", "rear"):
        raise ValueError(f"axle must be 'front' or 'rear', got {axle!r}")
    pub = dict(config["published"])
    for name in config.get("symmetry", {}).get("zeroed", []):
        if name not in pub:
            raise KeyError(f"symmetry.zeroed names unknown coefficient {name}")
        pub[name] = 0.0
    sc = config["scaling"]
    rel = config["relaxation"]
    lky = sc["LKY_FRONT"] if axle == "front" else sc["LKY_REAR"]
    return TyreCoefficients(
        fz0_n=pub["FNOMIN"] * sc["LFZO"],
        r0_m=pub["UNLOADED_RADIUS"],
        pcx1=pub["PCX1"] * sc["LCX"],
        pdx1=pub["PDX1"],
        pdx2=pub["PDX2"],
        pex1=pub["PEX1"] * sc["LEX"],
        pex2=pub["PEX2"] * sc["LEX"],
        pex3=pub["PEX3"] * sc["LEX"],
        pex4=pub["PEX4"],
        pkx1=pub["PKX1"] * sc["LKX"],
        pkx2=pub["PKX2"] * sc["LKX"],
        pkx3=pub["PKX3"],
        phx1=pub["PHX1"],
        phx2=pub["PHX2"],
        rbx1=pub["RBX1"] * sc["LXAL"],
        rbx2=pub["RBX2"],
        rcx1=pub["RCX1"],
        rhx1=pub["RHX1"],
        pcy1=pub["PCY1"] * sc["LCY"],
        pdy1=pub["PDY1"],
        pdy2=pub["PDY2"],
        pey1=pub["PEY1"] * sc["LEY"],
        pey2=pub["PEY2"] * sc["LEY"],
        pey3=pub["PEY3"],
        pky1=pub["PKY1"] * lky,
        pky2=pub["PKY2"],
        phy1=pub["PHY1"],
        phy2=pub["PHY2"],
        pvy1=pub["PVY1"],
        pvy2=pub["PVY2"],
        rby1=pub["RBY1"] * sc["LYKA"],
        rby2=pub["RBY2"],
        rby3=pub["RBY3"],
        rcy1=pub["RCY1"],
        rhy1=pub["RHY1"],
        rhy2=pub["RHY2"],
        rvy1=pub["RVY1"],
        rvy2=pub["RVY2"],
        rvy4=pub["RVY4"],
        rvy5=pub["RVY5"],
        rvy6=pub["RVY6"],
        qsy1=pub["QSY1"],
        sigma_alpha_m=rel["SIGMA_ALPHA_M"],
        sigma_kappa_m=rel["SIGMA_KAPPA_M"],
        v_low_mps=rel["V_LOW_MPS"],
    )


class MagicFormulaTyre:
    """Combined-slip Magic Formula tyre at zero camber.

    ``forces(kappa, alpha_rad, fz_n, mu_x, mu_y) -> (Fx, Fy)``: kappa (-), alpha (rad),
    Fz (N, >= 0, compressive), mu_x/mu_y = LMUX/LMUY road friction scaling (-); returns
    (Fx, Fy) in N in wheel axes. Sign convention: see the module docstring (positive alpha
    gives negative Fy; positive kappa gives positive Fx).
    """

    def __init__(self, coeffs: TyreCoefficients) -> None:
        self.coeffs = coeffs
        c = coeffs
        self.fz0 = c.fz0_n
        self.r0 = c.r0_m
        self.sigma_alpha = c.sigma_alpha_m
        self.sigma_kappa = c.sigma_kappa_m
        self.v_low = c.v_low_mps
        self.qsy1 = c.qsy1
        self._fz_max = _FZ_MAX_FACTOR * c.fz0_n
        # tuple of coefficients unpacked into locals in the hot path (fast attribute access)
        self._p = (
            c.fz0_n, c.pcx1, c.pdx1, c.pdx2, c.pex1, c.pex2, c.pex3, c.pex4, c.pkx1, c.pkx2,
            c.pkx3, c.phx1, c.phx2, c.rbx1, c.rbx2, c.rcx1, c.rhx1, c.pcy1, c.pdy1, c.pdy2,
            c.pey1, c.pey2, c.pey3, c.pky1, c.pky2, c.phy1, c.phy2, c.pvy1, c.pvy2, c.rby1,
            c.rby2, c.rby3, c.rcy1, c.rhy1, c.rhy2, c.rvy1, c.rvy2, c.rvy4, c.rvy5, c.rvy6,
        )

    # ------------------------------------------------------------------ derived quantities
    def cornering_stiffness(self, fz_n: float) -> float:
        """Pure-slip cornering stiffness dFy/dalpha at alpha = 0, N/rad (negative)."""
        c = self.coeffs
        fz = min(max(fz_n, 0.0), self._fz_max)
        u = fz / (c.pky2 * c.fz0_n)
        return c.pky1 * c.fz0_n * 2.0 * u / (1.0 + u * u)  # sin(2 atan u) = 2u/(1+u^2)

    def slip_stiffness(self, fz_n: float) -> float:
        """Pure-slip longitudinal slip stiffness dFx/dkappa at kappa = 0, N (positive)."""
        c = self.coeffs
        fz = min(max(fz_n, 0.0), self._fz_max)
        dfz = (fz - c.fz0_n) / c.fz0_n
        return fz * (c.pkx1 + c.pkx2 * dfz) * math.exp(c.pkx3 * dfz)

    def peak_mu(self, fz_n: float) -> tuple[float, float]:
        """Pure-slip peak friction (mu_x, |mu_y|) at mu scaling 1 and load fz_n (N), -."""
        c = self.coeffs
        dfz = (min(max(fz_n, 0.0), self._fz_max) - c.fz0_n) / c.fz0_n
        return c.pdx1 + c.pdx2 * dfz, abs(c.pdy1 + c.pdy2 * dfz)

    # ------------------------------------------------------------------ forces
    def forces(
        self, kappa: float, alpha_rad: float, fz_n: float, mu_x: float = 1.0, mu_y: float = 1.0
    ) -> tuple[float, float]:
        """Combined-slip (Fx, Fy) in N; see the class docstring for units and signs."""
        fx, fy, _ = self.forces_with_slope(kappa, alpha_rad, fz_n, mu_x, mu_y)
        return fx, fy

    def forces_with_slope(
        self, kappa: float, alpha_rad: float, fz_n: float, mu_x: float = 1.0, mu_y: float = 1.0
    ) -> tuple[float, float, float]:
        """(Fx N, Fy N, dFx/dkappa N): combined-slip forces plus the local longitudinal slip
        stiffness Gx_alpha * dFx0/dkappa (the dependence of Gx_alpha on kappa is neglected).
        The vehicle uses the slope as the Jacobian of its implicit wheel-spin step."""
        if not fz_n > _FZ_MIN_N:  # also catches NaN and denormal loads (Dx -> 0)
            return 0.0, 0.0, 0.0
        (fz0, pcx1, pdx1, pdx2, pex1, pex2, pex3, pex4, pkx1, pkx2, pkx3, phx1, phx2, rbx1,
         rbx2, rcx1, rhx1, pcy1, pdy1, pdy2, pey1, pey2, pey3, pky1, pky2, phy1, phy2, pvy1,
         pvy2, rby1, rby2, rby3, rcy1, rhy1, rhy2, rvy1, rvy2, rvy4, rvy5, rvy6) = self._p
        fz = fz_n if fz_n < self._fz_max else self._fz_max
        if mu_x < _MU_MIN:
            mu_x = _MU_MIN
        if mu_y < _MU_MIN:
            mu_y = _MU_MIN
        # slip outside the physical range is clamped (|kappa| <= 1 means up to full lock/spin
        # at the reference speed; the MF is flat there anyway); NaN slip counts as zero
        if kappa != kappa:
            kappa = 0.0
        if alpha_rad != alpha_rad:
            alpha_rad = 0.0
        clamped = kappa > 1.0 or kappa < -1.0
        if kappa > 1.0:
            kappa = 1.0
        elif kappa < -1.0:
            kappa = -1.0
        if alpha_rad > 1.5:
            alpha_rad = 1.5
        elif alpha_rad < -1.5:
            alpha_rad = -1.5
        dfz = (fz - fz0) / fz0
        atan = math.atan

        # --- longitudinal, pure slip (4.E9-4.E18)
        kx = kappa + phx1 + phx2 * dfz
        dx = (pdx1 + pdx2 * dfz) * mu_x * fz
        kxk = fz * (pkx1 + pkx2 * dfz) * math.exp(pkx3 * dfz)
        bx = kxk / (pcx1 * dx)
        ex = (pex1 + pex2 * dfz + pex3 * dfz * dfz) * (1.0 - pex4 * (1.0 if kx >= 0.0 else -1.0))
        if ex > 1.0:
            ex = 1.0
        bxk = bx * kx
        phi_x = bxk - ex * (bxk - atan(bxk))
        cx_phi = pcx1 * atan(phi_x)
        fx0 = dx * math.sin(cx_phi)
        # d Fx0 / d kappa (analytic), zero where the slip is clamped
        dfx0 = 0.0 if clamped else dx * math.cos(cx_phi) * pcx1 / (1.0 + phi_x * phi_x) * bx * (
            1.0 - ex + ex / (1.0 + bxk * bxk))

        # --- lateral, pure slip (4.E19-4.E30, gamma = 0)
        shy = phy1 + phy2 * dfz
        ay = alpha_rad + shy
        dy = (pdy1 + pdy2 * dfz) * mu_y * fz
        u = fz / (pky2 * fz0)
        kya = pky1 * fz0 * 2.0 * u / (1.0 + u * u)
        by = kya / (pcy1 * dy)
        ey = (pey1 + pey2 * dfz) * (1.0 - pey3 * (1.0 if ay >= 0.0 else -1.0))
        if ey > 1.0:
            ey = 1.0
        bya = by * ay
        fy0 = dy * math.sin(pcy1 * atan(bya - ey * (bya - atan(bya)))) + (
            pvy1 + pvy2 * dfz
        ) * mu_y * fz

        # --- combined slip weighting (4.E54-4.E67); cos(atan x) = 1/sqrt(1+x^2)
        t = rbx2 * kappa
        bxa = rbx1 / math.sqrt(1.0 + t * t)
        a_s = alpha_rad + rhx1
        gxa = math.cos(rcx1 * atan(bxa * a_s)) / math.cos(rcx1 * atan(bxa * rhx1))
        t = rby2 * (alpha_rad - rby3)
        byk = rby1 / math.sqrt(1.0 + t * t)
        shyk = rhy1 + rhy2 * dfz
        gyk = math.cos(rcy1 * atan(byk * (kappa + shyk))) / math.cos(rcy1 * atan(byk * shyk))
        # kappa-induced side force (zero when RVY1/RVY2 are symmetrised away)
        dvyk = mu_y * fz * (rvy1 + rvy2 * dfz) / math.sqrt(1.0 + (rvy4 * alpha_rad) ** 2)
        svyk = dvyk * math.sin(rvy5 * atan(rvy6 * kappa)) if dvyk != 0.0 else 0.0
        return gxa * fx0, gyk * fy0 + svyk, gxa * dfx0


def load_tyres(path: str | Path | None = None) -> tuple[MagicFormulaTyre, MagicFormulaTyre]:
    """(front, rear) tyres from a tyre TOML (default: the packaged one)."""
    config = load_tyre_config(path)
    return (
        MagicFormulaTyre(build_coefficients(config, "front")),
        MagicFormulaTyre(build_coefficients(config, "rear")),
    )


def make_vehicle_tyres() -> tuple[MagicFormulaTyre, MagicFormulaTyre]:
    """(front, rear) tyres exactly as the plant uses them (packaged ``params/tyre.toml``)."""
    return load_tyres(None)
