"""The yaw-moment effectiveness θ, learned jointly with the RHONN's yaw-rate weights.

The RHONN's known ΔM part on ωr is u = k·[(Ts − T_d)·ΔM_k + T_d·ΔM_{k−1}], k = wB/(2 Iz r)
from the nominal vehicle (controller/core/model/rhonn.py). A car that yaws harder or softer
than its nominal parameters say (a heavier body, another yaw inertia, tyres that answer a
wheel-torque difference differently) makes this gain wrong, and the one-step error it leaves
is fitted into the state weights, where the MPC cannot tell it from the car's own dynamics.

Here the yaw row's increment is Δωr = w_rᵀ φ + θ·u, and the 16 unknowns [w_r, θ] are
estimated by one Kalman filter with the regressor [φ, u] (the same EKF tuning and guards as
the state weights, controller/core/learning/ekf.py or ud_ekf.py). Estimated *jointly*: in
closed loop ΔM reacts to the state, so a regression of the ωr error on u alone attributes
part of the state-dependent model error to θ (a scalar NLMS on the innovation learned 1.15 on
the nominal car and 1.24 on a car with 1.3 × its yaw inertia); with φ in the same regression
that share goes to w_r. θ starts at 1 (eq. 17) with its own prior variance, drifts by the
weights' random walk q and is bounded to [theta_min, theta_max].
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.learning.ud_ekf import UdEkf


class YawGainFilter:
    """Joint filter of the yaw row's weights w_r (n_phi) and θ (-); regressor [φ, u] with u
    in rad/s (the known ΔM part at θ = 1)."""

    def __init__(self, n_phi: int, ekf: EkfConfig, w_row0: np.ndarray, theta_p0: float,
                 theta_min: float, theta_max: float, dtype: type = np.float64) -> None:
        """ekf: the state weights' tuning (its yaw-row r and zeta; θ drifts by the same random
        walk q per update as every weight); w_row0 (n_phi,): initial yaw-row weights, rad/s;
        theta_p0: prior variance of θ, -²; theta_min / theta_max: bounds of θ, -."""
        cfg = replace(ekf, r=(ekf.r[2],), zeta=(ekf.zeta[2],))
        w0 = np.zeros((1, n_phi + 1), dtype)
        w0[0, :n_phi] = w_row0
        w0[0, n_phi] = 1.0
        self.n_phi = n_phi
        self.filter: BatchedEkf | UdEkf = (UdEkf if ekf.form == "ud" else BatchedEkf)(
            1, n_phi + 1, cfg, w0=w0, dtype=dtype)
        self.theta_p0 = float(theta_p0)
        self.theta_min = float(theta_min)
        self.theta_max = float(theta_max)
        self._h = np.zeros(n_phi + 1, dtype)
        self._e = np.zeros(1, dtype)
        self.reset()

    @property
    def theta(self) -> float:
        """The learned ΔM effectiveness, - (1 = the nominal gain)."""
        return float(self.filter.W[0, self.n_phi])

    @property
    def w_row(self) -> np.ndarray:
        """The yaw row's weights (n_phi,), rad/s (a view)."""
        return self.filter.W[0, :self.n_phi]

    def _set_theta_variance(self, value: float) -> None:
        f = self.filter
        if isinstance(f, UdEkf):
            f.U[0, :, self.n_phi] = 0.0
            f.U[0, self.n_phi, self.n_phi] = 1.0
            f.D[0, self.n_phi] = value
        else:
            f.P[0, self.n_phi, :] = 0.0
            f.P[0, :, self.n_phi] = 0.0
            f.P[0, self.n_phi, self.n_phi] = value

    def reset(self) -> None:
        """Cold start: w_r = the initial weights, θ = 1 with variance theta_p0."""
        self.filter.reset()
        self._set_theta_variance(self.theta_p0)

    def update(self, phi: np.ndarray, u: float, e_r: float) -> bool:
        """One step: regressor φ (n_phi,), u rad/s, yaw-rate error e_r = ωr − χr rad/s.
        Returns True when the estimate changed (False: rejected, as the EKF rejects)."""
        h = self._h
        h[:self.n_phi] = phi
        h[self.n_phi] = u
        self._e[0] = e_r
        if not self.filter.update(h, self._e, True):
            return False
        w = self.filter.W
        w[0, self.n_phi] = min(max(float(w[0, self.n_phi]), self.theta_min), self.theta_max)
        return True

    def get_state(self) -> dict[str, np.ndarray]:
        """W (1, n_phi + 1) and P (1, n_phi + 1, n_phi + 1)."""
        return self.filter.get_state()

    def set_state(self, d: dict[str, np.ndarray]) -> None:
        """Restore get_state()."""
        self.filter.set_state(d)
