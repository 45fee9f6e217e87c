"""Vehicle dynamics: planar body + roll + pitch + four wheel-spin DoF + transient tyres + motors.

States (SI; ISO 8855 axes: x forward, y left, z up, + yaw = left):

* global position x_m, y_m (m) and yaw psi (rad);
* body velocities at the CG vx, vy (m/s, body axes) and yaw rate r (rad/s);
* sprung-mass roll phi (rad, + = right side down, i.e. a left turn rolls +) and pitch theta
  (rad, + = nose down) with their rates (rad/s): spring-damper DoFs that set the dynamic
  load transfer;
* wheel speeds omega[i] (rad/s), lagged slip angle alpha_t[i] (rad) and slip ratio
  kappa_t[i] (-) (tyre relaxation lengths), motor torques torque[i] (N·m). Wheel order
  FL, FR, RL, RR everywhere.

Integration, one fixed step ``dt`` (default 1 ms):

* relaxation lags: implicit Euler, ``x += a (x_kin - x) / (1 + a)``, ``a = dt * v / sigma``
  (unconditionally stable; v floored at V_LOW so the lag stays bounded at rest);
* wheel spin + longitudinal relaxation: the 2x2 linearly-implicit (Rosenbrock-Euler) step of
  [omega, kappa_t] with the tyre's analytic local slip stiffness dFx/dkappa as Jacobian
  (clipped at 0 past the peak); the spin mode is stiff at low speed, this keeps it stable;
* body, roll and pitch: semi-implicit (symplectic) Euler;
* motors: exact discretisation of the first-order lag, then the torque-speed-power envelope.

Load transfer uses the CG accelerations of the previous step (1 ms lag, breaks the algebraic
loop). The hot loop is scalar ``math`` arithmetic: numpy on 4-element vectors costs ~1 µs per
call and would dominate at 1 kHz.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from plant_sim import kernel
from plant_sim.motor import MotorModel
from plant_sim.params import VehicleParams

MuLookup = Callable[[float, float], float]


class VehicleModel:
    """The plant's rigid body, suspension, wheels, tyres and motors (no driver, no sensors)."""

    def __init__(self, params: VehicleParams) -> None:
        p = params
        self.p = p
        self.tyre_f, self.tyre_r = p.tyres()
        self.motor = MotorModel(
            p.peak_torque_nm, p.peak_power_w, p.time_constant_s, p.regen_fade_speed_radps,
            p.step_s,
        )
        L = p.wheelbase_m
        half = 0.5 * p.track_m
        # wheel contact points relative to the CG (m), FL FR RL RR
        self.wheel_x = (p.lf_m, p.lf_m, -p.lr_m, -p.lr_m)
        self.wheel_y = (half, -half, half, -half)
        fzf, fzr = p.static_wheel_loads_n
        self.fz_static = (fzf, fzf, fzr, fzr)
        ms = p.sprung_mass_kg
        mu_c = p.unsprung_mass_per_corner_kg
        # sprung-mass CG height from m*h = ms*hs + 4*mu*r (unsprung CG at wheel centre)
        self.hs = (p.mass_kg * p.cg_height_m - 4.0 * mu_c * p.wheel_radius_m) / ms
        self.h_roll_arm = self.hs - p.roll_axis_height_m
        self.h_pitch_arm = self.hs - p.pitch_axis_height_m
        if self.h_roll_arm <= 0 or self.h_pitch_arm <= 0:
            raise ValueError("roll/pitch axis must lie below the sprung-mass CG")
        self.L = L
        self.max_delta = math.radians(p.max_road_wheel_angle_deg)
        self.use_kernel = kernel.enabled()
        if self.use_kernel:
            self._init_kernel()
        self.reset()

    def _init_kernel(self) -> None:
        """Constants and work arrays of the compiled kernel (plant_sim/kernel.py)."""
        p, m = self.p, self.motor
        tf, tr = self.tyre_f, self.tyre_r
        c = np.zeros(kernel.N_CONST)
        L = self.L
        ms = p.sprung_mass_kg
        mu_tot = 4.0 * p.unsprung_mass_per_corner_kg
        values = {
            kernel.C_DT: p.step_s, kernel.C_M: p.mass_kg, kernel.C_IZ: p.yaw_inertia_kgm2,
            kernel.C_R: p.wheel_radius_m, kernel.C_HW: p.step_s / p.wheel_inertia_kgm2,
            kernel.C_G: p.gravity_mps2, kernel.C_MS: ms, kernel.C_MUTOT: mu_tot,
            kernel.C_HRA: p.roll_axis_height_m, kernel.C_HPA: p.pitch_axis_height_m,
            kernel.C_HPHI: self.h_roll_arm, kernel.C_HTHETA: self.h_pitch_arm,
            kernel.C_KPHI: p.roll_stiffness_nm_per_rad,
            kernel.C_CPHI: p.roll_damping_nms_per_rad,
            kernel.C_KTH: p.pitch_stiffness_nm_per_rad,
            kernel.C_CTH: p.pitch_damping_nms_per_rad,
            kernel.C_CHI: p.roll_stiffness_front_share, kernel.C_IPHI: p.roll_inertia_kgm2,
            kernel.C_ITH: p.pitch_inertia_kgm2, kernel.C_L: L, kernel.C_INVWB: 1.0 / p.track_m,
            kernel.C_MSF: ms * p.lr_m / L, kernel.C_MSR: ms * p.lf_m / L,
            kernel.C_MUAX: 0.5 * mu_tot,
            kernel.C_DRAGK: 0.5 * p.air_density_kgpm3 * p.drag_area_m2,
            kernel.C_FRR: p.rolling_resistance_coeff, kernel.C_VRR: p.rr_smoothing_speed_mps,
            kernel.C_VLOW: tf.v_low, kernel.C_SIGAF: tf.sigma_alpha,
            kernel.C_SIGAR: tr.sigma_alpha, kernel.C_SIGKF: tf.sigma_kappa,
            kernel.C_SIGKR: tr.sigma_kappa, kernel.C_LAG: m.lag_gain,
            kernel.C_TPK: m.peak_torque_nm, kernel.C_PPK: m.peak_power_w,
            kernel.C_WBASE: m.base_speed_radps, kernel.C_WFADE: m.regen_fade_speed_radps,
            kernel.C_MAXDELTA: self.max_delta, kernel.C_FZMAXF: tf._fz_max,
            kernel.C_FZMAXR: tr._fz_max,
        }
        for index, value in values.items():
            c[index] = value
        self._k_const = c
        self._k_tyre = np.array([tf._p, tr._p], dtype=np.float64)
        self._k_wx = np.array(self.wheel_x, dtype=np.float64)
        self._k_wy = np.array(self.wheel_y, dtype=np.float64)
        self._k_fzst = np.array(self.fz_static, dtype=np.float64)
        self._k_state = np.zeros(kernel.N_STATE)
        self._k_wheels = np.zeros((8, 4))
        self._k_cmd = np.zeros(4)
        # zero steps: loads (or compiles) the kernel now, during set-up, not in the first cycle
        kernel.advance_kernel(np.zeros(0), self._k_cmd, self._k_state, self._k_wheels, c,
                              self._k_tyre, self._k_wx, self._k_wy, self._k_fzst)

    # ------------------------------------------------------------------ state
    def reset(self, x: float = 0.0, y: float = 0.0, psi: float = 0.0, vx: float = 0.0) -> None:
        """Straight-ahead free rolling at speed vx (m/s) from (x, y) m with heading psi rad."""
        self.x, self.y, self.psi = x, y, psi
        self.vx, self.vy, self.r = vx, 0.0, 0.0
        self.phi = self.dphi = self.theta = self.dtheta = 0.0
        w = vx / self.p.wheel_radius_m
        self.omega = [w, w, w, w]
        self.alpha_t = [0.0, 0.0, 0.0, 0.0]
        self.kappa_t = [0.0, 0.0, 0.0, 0.0]
        self.torque = [0.0, 0.0, 0.0, 0.0]
        self.ax = self.ay = 0.0  # CG acceleration in body axes, m/s^2 (last step)
        self.fz = list(self.fz_static)
        self.fx = [0.0, 0.0, 0.0, 0.0]  # wheel-axes tyre forces, N (last step)
        self.fy = [0.0, 0.0, 0.0, 0.0]
        self.mu = [1.0, 1.0, 1.0, 1.0]
        self.delta = 0.0
        self.time_s = 0.0

    def wheel_positions(self) -> list[tuple[float, float]]:
        """Global (x, y) of the four contact points, m."""
        c, s = math.cos(self.psi), math.sin(self.psi)
        return [
            (self.x + c * wx - s * wy, self.y + s * wx + c * wy)
            for wx, wy in zip(self.wheel_x, self.wheel_y, strict=True)
        ]

    @property
    def beta(self) -> float:
        """Sideslip angle at the CG, atan2(vy, vx), rad."""
        return math.atan2(self.vy, self.vx) if (self.vx != 0.0 or self.vy != 0.0) else 0.0

    # ------------------------------------------------------------------ integration
    def advance(
        self,
        deltas_rad: Sequence[float],
        torque_cmd_nm: Sequence[float],
        mu_const: float | None,
        mu_lookup: MuLookup | None = None,
    ) -> None:
        """Integrate ``len(deltas_rad)`` fixed steps of ``p.step_s``.

        deltas_rad: road-wheel angle of both front wheels at each step, rad (+ left).
        torque_cmd_nm: motor torque commands FL, FR, RL, RR, N·m (already saturated).
        mu_const: road friction if uniform (fast path), else None and ``mu_lookup(x, y)``
        gives mu at a global point (m).
        """
        if mu_const is not None and self.use_kernel:
            self._advance_kernel(deltas_rad, torque_cmd_nm, mu_const)
            return
        p = self.p
        dt = p.step_s
        m = p.mass_kg
        Iz = p.yaw_inertia_kgm2
        R = p.wheel_radius_m
        h_w = dt / p.wheel_inertia_kgm2
        g = p.gravity_mps2
        ms = p.sprung_mass_kg
        mu_tot = 4.0 * p.unsprung_mass_per_corner_kg
        hra, hpa = p.roll_axis_height_m, p.pitch_axis_height_m
        hphi, htheta = self.h_roll_arm, self.h_pitch_arm
        k_phi, c_phi = p.roll_stiffness_nm_per_rad, p.roll_damping_nms_per_rad
        k_th, c_th = p.pitch_stiffness_nm_per_rad, p.pitch_damping_nms_per_rad
        chi = p.roll_stiffness_front_share
        I_phi, I_th = p.roll_inertia_kgm2, p.pitch_inertia_kgm2
        L = self.L
        inv_wb = 1.0 / p.track_m
        ms_f, ms_r = ms * p.lr_m / L, ms * p.lf_m / L
        mu_ax = 0.5 * mu_tot  # unsprung mass per axle, kg
        drag_k = 0.5 * p.air_density_kgpm3 * p.drag_area_m2
        f_rr = p.rolling_resistance_coeff
        v_rr = p.rr_smoothing_speed_mps
        tf, tr = self.tyre_f, self.tyre_r
        ff, fr_ = tf.forces_with_slope, tr.forces_with_slope
        v_low = tf.v_low
        sig_a_f, sig_a_r = tf.sigma_alpha, tr.sigma_alpha
        sig_k_f, sig_k_r = tf.sigma_kappa, tr.sigma_kappa
        motor = self.motor
        lag = motor.lag_gain
        t_pk, p_pk, w_base = motor.peak_torque_nm, motor.peak_power_w, motor.base_speed_radps
        w_fade = motor.regen_fade_speed_radps
        max_delta = self.max_delta
        wxs, wys = self.wheel_x, self.wheel_y
        fz_st = self.fz_static
        cmd = tuple(float(t) for t in torque_cmd_nm)

        x, y, psi = self.x, self.y, self.psi
        vx, vy, r = self.vx, self.vy, self.r
        phi, dphi, theta, dtheta = self.phi, self.dphi, self.theta, self.dtheta
        ax, ay = self.ax, self.ay
        omega, alpha_t, kappa_t, torque = self.omega, self.alpha_t, self.kappa_t, self.torque
        fz_out, fx_out, fy_out, mu_out = self.fz, self.fx, self.fy, self.mu
        atan2, cos, sin, sqrt = math.atan2, math.cos, math.sin, math.sqrt
        delta = self.delta
        if mu_const is not None:
            mu_out[0] = mu_out[1] = mu_out[2] = mu_out[3] = mu_const

        for delta_in in deltas_rad:
            delta = delta_in if -max_delta <= delta_in <= max_delta else (
                max_delta if delta_in > 0 else -max_delta)
            cd, sd = cos(delta), sin(delta)
            cpsi, spsi = cos(psi), sin(psi)

            # --- normal loads: static + longitudinal (pitch DoF) + lateral (roll DoF) transfer
            m_theta = k_th * theta + c_th * dtheta
            d_long = (ms * hpa * ax + mu_tot * R * ax - m_theta) / L  # to the rear axle, N
            m_phi = k_phi * phi + c_phi * dphi
            d_lat_f = (chi * m_phi + ms_f * hra * ay + mu_ax * R * ay) * inv_wb  # to the right
            d_lat_r = ((1.0 - chi) * m_phi + ms_r * hra * ay + mu_ax * R * ay) * inv_wb
            fz0 = fz_st[0] - 0.5 * d_long - d_lat_f
            fz1 = fz_st[1] - 0.5 * d_long + d_lat_f
            fz2 = fz_st[2] + 0.5 * d_long - d_lat_r
            fz3 = fz_st[3] + 0.5 * d_long + d_lat_r
            fz_out[0] = fz0 if fz0 > 0.0 else 0.0
            fz_out[1] = fz1 if fz1 > 0.0 else 0.0
            fz_out[2] = fz2 if fz2 > 0.0 else 0.0
            fz_out[3] = fz3 if fz3 > 0.0 else 0.0

            if mu_const is None and mu_lookup is not None:
                for i in range(4):
                    wx, wy = wxs[i], wys[i]
                    mu_out[i] = mu_lookup(x + cpsi * wx - spsi * wy, y + spsi * wx + cpsi * wy)

            sum_fx = 0.0
            sum_fy = 0.0
            mz = 0.0
            for i in range(4):
                wx, wy = wxs[i], wys[i]
                fz = fz_out[i]
                mu = mu_out[i]
                vxi = vx - r * wy
                vyi = vy + r * wx
                if i < 2:
                    vxw = vxi * cd + vyi * sd
                    vyw = vyi * cd - vxi * sd
                    tyre = ff
                    sig_a, sig_k = sig_a_f, sig_k_f
                else:
                    vxw, vyw = vxi, vyi
                    tyre = fr_
                    sig_a, sig_k = sig_a_r, sig_k_r
                avx = vxw if vxw >= 0.0 else -vxw
                den = avx if avx > v_low else v_low  # low-speed blend of the slip denominators
                speed = sqrt(vxw * vxw + vyw * vyw)
                if speed < v_low:
                    speed = v_low
                # slip angle: implicit first-order relaxation towards the kinematic value
                a_a = dt * speed / sig_a
                at = (alpha_t[i] + a_a * atan2(vyw, den)) / (1.0 + a_a)
                alpha_t[i] = at
                w = omega[i]
                kt = kappa_t[i]
                fxw, fyw, slope = tyre(kt, at, fz, mu, mu)
                if slope < 0.0:
                    slope = 0.0  # beyond the peak the mode is physically unstable: no damping

                # motor: first-order lag then the torque-speed-power envelope
                tq = torque[i] + (cmd[i] - torque[i]) * lag
                aw = w if w >= 0.0 else -w
                t_max = t_pk if aw <= w_base else p_pk / aw
                fade = w / w_fade
                t_min = -t_max * (0.0 if fade < 0.0 else (1.0 if fade > 1.0 else fade))
                tq = t_max if tq > t_max else (t_min if tq < t_min else tq)
                torque[i] = tq

                # rolling resistance moment, ramped in near standstill
                s_rr = w * R / v_rr
                s_rr = 1.0 if s_rr > 1.0 else (-1.0 if s_rr < -1.0 else s_rr)
                f_net = tq - R * fxw - f_rr * fz * R * s_rr  # net wheel torque, N·m

                # linearly-implicit step of [omega, kappa_t] (see module docstring)
                a_k = dt * speed / sig_k
                c_k = R / den
                e_k = (w * R - vxw) / den - kt
                gk = h_w * R * slope * a_k / (1.0 + a_k)
                d_w = (h_w * f_net - gk * e_k) / (1.0 + gk * c_k)
                omega[i] = w + d_w
                kappa_t[i] = kt + a_k * (e_k + c_k * d_w) / (1.0 + a_k)

                fx_out[i] = fxw
                fy_out[i] = fyw
                if i < 2:
                    fxb = fxw * cd - fyw * sd
                    fyb = fxw * sd + fyw * cd
                else:
                    fxb, fyb = fxw, fyw
                sum_fx += fxb
                sum_fy += fyb
                mz += wx * fyb - wy * fxb

            # --- body: CG accelerations (body axes) and semi-implicit Euler
            ax = (sum_fx - drag_k * vx * (vx if vx >= 0.0 else -vx)) / m
            ay = sum_fy / m
            vx += dt * (ax + r * vy)
            vy += dt * (ay - r * vx)
            r += dt * mz / Iz
            psi += dt * r
            x += dt * (vx * cpsi - vy * spsi)
            y += dt * (vx * spsi + vy * cpsi)
            # roll (+ right side down) and pitch (+ nose down) of the sprung mass
            dphi += dt * (ms * hphi * (ay + g * phi) - k_phi * phi - c_phi * dphi) / I_phi
            phi += dt * dphi
            dtheta += dt * (ms * htheta * (g * theta - ax) - k_th * theta - c_th * dtheta) / I_th
            theta += dt * dtheta

        n = len(deltas_rad)
        self.time_s += n * dt
        self.x, self.y, self.psi = x, y, psi
        self.vx, self.vy, self.r = vx, vy, r
        self.phi, self.dphi, self.theta, self.dtheta = phi, dphi, theta, dtheta
        self.ax, self.ay = ax, ay
        self.delta = delta

    def _advance_kernel(self, deltas_rad: Sequence[float], torque_cmd_nm: Sequence[float],
                        mu_const: float) -> None:
        """``advance`` through the compiled kernel (uniform friction): the same arithmetic,
        state copied in and out as Python floats (the trace stays bit-identical)."""
        st, wh = self._k_state, self._k_wheels
        st[:] = (self.x, self.y, self.psi, self.vx, self.vy, self.r, self.phi, self.dphi,
                 self.theta, self.dtheta, self.ax, self.ay, self.delta)
        wh[kernel.OMEGA] = self.omega
        wh[kernel.ALPHA_T] = self.alpha_t
        wh[kernel.KAPPA_T] = self.kappa_t
        wh[kernel.TORQUE] = self.torque
        wh[kernel.MU] = mu_const
        cmd = self._k_cmd
        cmd[:] = [float(t) for t in torque_cmd_nm]
        deltas = np.asarray(deltas_rad, dtype=np.float64)
        kernel.advance_kernel(deltas, cmd, st, wh, self._k_const, self._k_tyre, self._k_wx,
                              self._k_wy, self._k_fzst)
        (self.x, self.y, self.psi, self.vx, self.vy, self.r, self.phi, self.dphi, self.theta,
         self.dtheta, self.ax, self.ay, self.delta) = st.tolist()
        rows = wh.tolist()
        self.omega[:] = rows[kernel.OMEGA]
        self.alpha_t[:] = rows[kernel.ALPHA_T]
        self.kappa_t[:] = rows[kernel.KAPPA_T]
        self.torque[:] = rows[kernel.TORQUE]
        self.fz[:] = rows[kernel.FZ]
        self.fx[:] = rows[kernel.FX]
        self.fy[:] = rows[kernel.FY]
        self.mu[:] = rows[kernel.MU]
        self.time_s += len(deltas_rad) * self.p.step_s
