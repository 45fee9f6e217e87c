"""Two time scales for the learned map: a slowly updated copy of the RHONN weights.

The EKF (learning/ekf.py) adapts W within a few 50 ms steps, so W fits the transient the car
is in. A map that has just fitted the transient has its equilibrium just behind the current
state: Algorithm 1 on the live W returned ωrd ≈ 0.97 × the measured yaw rate on dlc-paper
(measured). The references can instead read a copy that follows W with a first-order lag,

    W_slow ← W_slow + (1 − exp(−Ts/τ)) · (W − W_slow)          (τ = tau_s, s)

which averages the fast fits over ≈ τ seconds of driving. τ = 0 means "the live weights"
(W_slow is W itself, no copy). The copy starts at the first weights it sees (the cold-start
W0 = 0) and is reset with the model.

Also here: :func:`collapse`, the (Vy, ωr) bilinear collapse of any weight matrix at fixed
Vx and δw (the same algebra as ``RhonnModel.bilinear_coefficients``, for a W that is not the
model's own).
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.model.rhonn import MONO_INDEX, TFAC_INDEX, RhonnModel


def collapse(w: np.ndarray, xi_vx: float, xi_dw: float, w4: np.ndarray,
             out: np.ndarray) -> np.ndarray:
    """Coefficients C (3, 4) with W φ = C0 + C1 ξ2 + C2 ξ3 + C3 ξ2 ξ3 at fixed ξ1 = S(Vx),
    ξ4 = S(δw) (dimensionless), written into ``out``. ``w4`` is (3, 4, 4) scratch."""
    w4[:, MONO_INDEX, TFAC_INDEX] = w
    t = np.array((1.0, xi_vx, xi_dw, xi_vx * xi_dw))
    np.matmul(w4, t, out=out)
    return out


class SlowWeights:
    """First-order-lag copy of a RHONN's weights (see the module docstring).

    tau_s: time constant, s (0 = no copy: ``W`` is the model's live matrix). ts: update
    period, s (one ``update()`` per reference call)."""

    def __init__(self, model: RhonnModel, tau_s: float, ts: float,
                 key: str = "ref.w_slow") -> None:
        self.model = model
        self.key = key
        self.tau_s = max(float(tau_s), 0.0)
        self.alpha = 1.0 - math.exp(-ts / self.tau_s) if self.tau_s > 0.0 else 1.0
        self._copy = np.array(model.W, dtype=float)
        self._w4 = np.zeros((3, 4, 4))
        self._coef = np.zeros((3, 4))
        self._started = False

    @property
    def W(self) -> np.ndarray:
        """The weights the references read, (3, 15) in state units."""
        return self.model.W if self.tau_s <= 0.0 else self._copy

    def update(self) -> None:
        """One period of the lag (no-op for τ = 0). Non-finite live weights are skipped."""
        if self.tau_s <= 0.0:
            return
        w = self.model.W
        if not np.isfinite(w.sum()):
            return
        if not self._started:
            self._copy[:] = w
            self._started = True
            return
        self._copy += self.alpha * (w - self._copy)

    def coefficients(self, vx: float, delta_w: float) -> np.ndarray:
        """Bilinear (Vy, ωr) coefficients (3, 4) of the slow map at Vx m/s, δw rad."""
        m = self.model
        return collapse(self.W, m.xi(0, vx), m.xi(3, delta_w), self._w4, self._coef)

    def reset(self) -> None:
        """Forget the copy (it restarts at the next live weights)."""
        self._copy[:] = self.model.W
        self._started = False

    def get_state(self) -> dict[str, np.ndarray | float]:
        """The copy, (3, 15)."""
        return {self.key: self._copy.copy(), f"{self.key}_started": float(self._started)}

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state() (missing keys: restart the copy)."""
        if self.key in d:
            self._copy[:] = np.asarray(d[self.key], dtype=float)
            self._started = bool(d.get(f"{self.key}_started", 1.0))
        else:
            self.reset()
