"""Four-wheel chassis geometry and quasi-static normal loads shared by the 7-DoF models.

Wheel order 1 FL, 2 FR, 3 RL, 4 RR. Body axes ISO 8855 (x forward, y left). The contact
point of wheel i sits at (x_i, y_i) = (+lf or −lr, ±wB/2) from the CG, so its velocity is
u_i = vx − y_i·r, v_i = vy + x_i·r, and a force (FX, FY) there gives the yaw moment
x_i·FY − y_i·FX.

Normal loads (N), static + quasi-static transfer with CG height h (no roll/pitch dynamics)::

    Fz_i = Fz_static,i ∓ m·ax·h/(2L) (front −, rear +)
                       ∓ m·ay·h/wB · (lr/L front, lf/L rear) (left −, right +)

The lateral transfer is split between the axles in proportion to their static load (the
controller knows no roll stiffnesses). The models clamp loads to
[FZ_MIN_N, min(m·g, FZ_CAP_FACTOR·Fz0)] (see tyre.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from controller.core.model.tyre import FZ_MIN_N
from controller.core.params import VehicleParams

G_MPS2 = 9.81
"""Gravity, m/s²."""


@dataclass(frozen=True, slots=True)
class Corner:
    """One wheel: position, load model and tyre-stiffness split.

    x_m, y_m: contact point from the CG, m. front: steered axle. fz_static_n: N.
    kx_ax, ky_ay: load transfer per unit ax / ay, N/(m/s²). c_lin: linear cornering stiffness
    of this wheel (positive, N/rad; half the axle's Table 1 value).
    """

    x_m: float
    y_m: float
    front: bool
    fz_static_n: float
    kx_ax: float
    ky_ay: float
    c_lin: float


def make_corners(p: VehicleParams) -> tuple[Corner, Corner, Corner, Corner]:
    """The four corners FL, FR, RL, RR of vehicle p."""
    L = p.wheelbase_m
    tw = 0.5 * p.track_m
    m, h = p.mass_kg, p.cg_height_m
    fzf = m * G_MPS2 * p.lr_m / (2.0 * L)
    fzr = m * G_MPS2 * p.lf_m / (2.0 * L)
    kx = m * h / (2.0 * L)
    kyf = m * h / p.track_m * p.lr_m / L
    kyr = m * h / p.track_m * p.lf_m / L
    cf = -0.5 * p.cf_axle_n_per_rad  # positive per-wheel stiffness
    cr = -0.5 * p.cr_axle_n_per_rad
    return (
        Corner(p.lf_m, tw, True, fzf, -kx, -kyf, cf),
        Corner(p.lf_m, -tw, True, fzf, -kx, kyf, cf),
        Corner(-p.lr_m, tw, False, fzr, kx, -kyr, cr),
        Corner(-p.lr_m, -tw, False, fzr, kx, kyr, cr),
    )


def clamp_load(fz_n: float, fz_max_n: float) -> tuple[float, float]:
    """(clamped load N, derivative factor 1.0 inside / 0.0 at a bound)."""
    if fz_n < FZ_MIN_N:
        return FZ_MIN_N, 0.0
    if fz_n > fz_max_n:
        return fz_max_n, 0.0
    return fz_n, 1.0
