"""Data types and protocols shared by every controller in the core.

Everything here is pure: no I/O, no clocks. All physical quantities are SI
(m, s, rad, N, N·m, kg) unless a name says otherwise. Sign convention ISO 8855:
x forward, y left, z up; + yaw rate and + steering = left turn. Wheel order is
1 FL, 2 FR, 3 RL, 4 RR everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol

import numpy as np


class QpStatus(IntEnum):
    """Outcome of the per-step optimisation, as carried in the CTRL_STATUS frame (3 bits)."""

    SOLVED = 0
    SOLVED_INACCURATE = 1
    MAX_ITER = 2
    FAILED = 3  # infeasible, non-convex, NaN, or any solver error
    NOT_RUN = 4  # passive controller, or the step was skipped (invalid inputs, disabled)
    FALLBACK = 5  # solver failed and the defined fallback ΔM was used


@dataclass(slots=True)
class ControllerInputs:
    """Decoded bus values for one controller step (one instance is reused; no allocation).

    swa_rad: steering-wheel angle, rad (+ left).
    accel_pedal, brake_pedal: pedal positions, 0..1 (dimensionless).
    yaw_rate: rad/s (+ left). ax, ay: body-fixed accelerations, m/s^2.
    wheel_speeds: wheel angular speeds FL, FR, RL, RR, rad/s.
    vx, vy: estimated body velocities at the CG, m/s (from the upstream estimator frame).
    stab_enable: the driver/scenario enables the stability function (else ΔM = 0).
    sensors_valid: all motion/wheel/estimate frames valid and fresh; False forces ΔM = 0
        and freezes learning.
    """

    swa_rad: float = 0.0
    accel_pedal: float = 0.0
    brake_pedal: float = 0.0
    yaw_rate: float = 0.0
    ax: float = 0.0
    ay: float = 0.0
    wheel_speeds: np.ndarray = field(default_factory=lambda: np.zeros(4))
    vx: float = 0.0
    vy: float = 0.0
    stab_enable: bool = True
    sensors_valid: bool = True


@dataclass(slots=True)
class ControllerOutputs:
    """Result of one controller step (one instance is reused; no allocation).

    torques: wheel torque commands FL, FR, RL, RR, N·m (+ drives forward).
    total_torque: driver's total torque demand Tt, N·m.
    delta_m: commanded torque difference ΔM = T2 + T4 - T1 - T3, N·m (+ turns left).
    yaw_rate_ref: rad/s. vy_ref: m/s. beta_ref: rad.
    qp_status: QpStatus value. qp_iterations: solver iterations this step (0 if not run).
    fallback: True when the solver failed and the fallback ΔM was used.
    model_prediction: the model's one-step-ahead estimate of [vx m/s, vy m/s, r rad/s]
        made at this step for the next step (for fidelity evaluation; NaN if none).
    """

    torques: np.ndarray = field(default_factory=lambda: np.zeros(4))
    total_torque: float = 0.0
    delta_m: float = 0.0
    yaw_rate_ref: float = 0.0
    vy_ref: float = 0.0
    beta_ref: float = 0.0
    qp_status: int = int(QpStatus.NOT_RUN)
    qp_iterations: int = 0
    fallback: bool = False
    model_prediction: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


@dataclass(slots=True)
class PredictionContext:
    """Inputs held constant over the horizon (paper eq. 21: weights and Tt fixed).

    delta_w: road-wheel steering angle, rad (+ left). total_torque: Tt, N·m.
    ts: model sampling time, s. wheel_speeds: measured wheel speeds FL..RR, rad/s
    (for models that carry wheel-spin states). delta_m_prev: ΔM applied during the previous
    period, N·m (for models with an actuator dead time, see rhonn.RhonnConfig; the physics
    baselines ignore it).
    """

    delta_w: float = 0.0
    total_torque: float = 0.0
    ts: float = 0.05
    wheel_speeds: np.ndarray = field(default_factory=lambda: np.zeros(4))
    delta_m_prev: float = 0.0


class PredictionModel(Protocol):
    """Discrete-time model x[k+1] = f(x[k], ΔM[k]; ctx) used inside the NMPC horizon.

    x has nx >= 3 entries; x[0:3] are always [vx m/s, vy m/s, r rad/s]; further entries
    are model-internal (e.g. wheel speeds). ΔM in N·m. Implementations write into the
    caller's preallocated arrays and never allocate in these calls.
    """

    nx: int

    def initial_state(self, inputs: ControllerInputs, out: np.ndarray) -> None:
        """Fill out (nx,) with the measured state at the current step."""

    def predict(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                out: np.ndarray) -> None:
        """One step of the model: out (nx,) = f(x, ΔM)."""

    def linearize(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                  a_out: np.ndarray, b_out: np.ndarray) -> None:
        """Jacobians at (x, ΔM): a_out (nx, nx) = ∂f/∂x, b_out (nx,) = ∂f/∂ΔM (per N·m)."""


class ReferenceGenerator(Protocol):
    """Steady-state yaw-rate / lateral-velocity references (paper eq. 18–20)."""

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """Return (yaw_rate_ref rad/s, vy_ref m/s, beta_ref rad) for the current step."""


class StateEstimator(Protocol):
    """Open-loop or learning state estimator for the fidelity study (paper Tables 2–3)."""

    def reset(self) -> None:
        """Return to the cold-start state."""

    def step(self, inputs: ControllerInputs, torques: np.ndarray, dt: float) -> np.ndarray:
        """Advance by dt s with the applied wheel torques (4,) N·m; return the estimate of
        [vx m/s, vy m/s, r rad/s] at the new time (a view that the next call may overwrite)."""


class Controller(Protocol):
    """A complete controller: references + prediction + QP + allocation."""

    name: str
    ts: float  # controller period, s

    def reset(self) -> None:
        """Cold start: learned weights, warm starts and filters back to their initial values."""

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        """One full controller period (learning, references, QP, allocation)."""

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        """Between MPC updates: re-allocate the held ΔM with the fresh pedal torque Tt."""


class AdaptiveModel(PredictionModel, Protocol):
    """A PredictionModel that learns online (series-parallel), e.g. the RHONN.

    Per controller step: ``observe`` first (learn from the prediction made last step),
    then, once ΔM is decided, ``record`` the one-step prediction for the next step.
    """

    def observe(self, x_meas: np.ndarray, learn: bool) -> bool:
        """Learn from x_meas (nx,) vs the recorded prediction; frozen when learn is False.
        Returns True if the model changed."""

    def record(self, x_meas: np.ndarray, delta_m: float, ctx: PredictionContext,
               out: np.ndarray) -> None:
        """out (nx,) = f(x_meas, ΔM N·m); remembered for the next observe."""

    def forget_record(self) -> None:
        """Drop the pending prediction (the next observe does nothing)."""
