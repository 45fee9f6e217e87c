/* 7-DoF vehicle model reduced for NMPC prediction (NMPC-MF "7dof-mf" / "7dof-li"), nx = 3.
 * Python reference: controller/core/model/seven_dof.py (SevenDofPrediction), with
 * chassis.py (corners, normal loads), tyre.py (mf_tyre.h) and _substep.py (substep.h).
 *
 * States x = [vx m/s, vy m/s, r rad/s]; input DeltaM N m; ctx->delta_w (rad, front wheels)
 * and ctx->total_torque Tt (N m) held over the step of ctx->ts seconds.
 * Quasi-steady longitudinal slip: Fx_i = T_i / R with T_FL = T_RL = (Tt - DeltaM)/4,
 * T_FR = T_RR = (Tt + DeltaM)/4. Lateral force per wheel at the ISO slip angle
 * alpha = atan2(v_y,w, max(|v_x,w|, 1 m/s)): Fy = -MF(alpha, Fz) (mf) or Fy = -c_lin alpha
 * (linear, c_lin = half the axle's |Table 1| stiffness). Normal loads static + quasi-static
 * transfer with ax = Tt/(m R), ay = vx r, clamped to [FZ_MIN, min(m g, 2 Fz0)].
 *   dvx/dt = SUM FX/m + vy r - f g ramp(vx) - k vx |vx| / m
 *   dvy/dt = SUM FY/m - vx r,   dr/dt = SUM (x_i FY_i - y_i FX_i) / Iz
 * Wheel order FL, FR, RL, RR; body axes ISO 8855 (x forward, y left). */
#ifndef RH_SEVEN_DOF_H
#define RH_SEVEN_DOF_H

#include <stddef.h>

#include "mf_tyre.h"
#include "rh_params.h"
#include "rh_real.h"

#define RH_SEVEN_DOF_G_MPS2 9.81 /* gravity, m/s^2 (chassis.G_MPS2) */

/* Configuration (Python: MfTyreSet from load_mf_tyres() + the model kind + h_max). */
typedef struct {
  rh_mf_curve_config_t front_lateral; /* MfTyreSet.front.lateral */
  rh_mf_curve_config_t rear_lateral;  /* MfTyreSet.rear.lateral */
  double mu_nominal;      /* friction scaling of the MF, - ([controller] mu_estimate if > 0) */
  double rolling_coeff;   /* rolling resistance f (force f m g), - */
  double drag_n_per_mps2; /* aero k (force k vx |vx|), N/(m/s)^2 */
  double ramp_speed_mps;  /* rolling resistance ramps in below this speed, m/s (> 0) */
  double h_max_s;         /* sub-step bound, s (reference default 0.05) */
  int linear;             /* 1: "7dof-li" linear tyres, 0: "7dof-mf" Magic Formula */
} rh_seven_dof_config_t;

/* One corner (chassis.Corner + its lateral curve), working precision. */
typedef struct {
  real_t x;         /* contact point from the CG, forward, m */
  real_t y;         /* contact point from the CG, left, m */
  real_t fz_static; /* static load, N */
  real_t kx_ax;     /* load transfer per ax, N/(m/s^2) */
  real_t ky_ay;     /* load transfer per ay, N/(m/s^2) */
  real_t c_lin;     /* linear cornering stiffness (positive), N/rad */
  real_t side;      /* +1 right wheel (T = (Tt+DeltaM)/4), -1 left, - */
  real_t fz_cap;    /* load cap min(m g, 2 Fz0), N */
  int front;        /* 1: steered front wheel */
  rh_mf_curve_t lateral; /* lateral MF curve of this axle */
} rh_seven_dof_wheel_t;

typedef struct {
  double h_max_s;    /* sub-step bound, s */
  double stiff_rate; /* bound of |lambda| vx of the lateral dynamics, m/s^2 */
  real_t m;          /* mass, kg */
  real_t iz;         /* yaw inertia, kg m^2 */
  real_t radius;     /* wheel radius R, m */
  real_t mu;         /* friction scaling of the MF, - */
  real_t rr;         /* rolling resistance f g at full ramp, m/s^2 */
  real_t rr_ramp;    /* ramp speed, m/s */
  real_t kd;         /* drag k / m, 1/m */
  int mf;            /* 1: MF tyres, 0: linear */
  rh_seven_dof_wheel_t w[4]; /* FL, FR, RL, RR */
} rh_seven_dof_t;

void rh_seven_dof_init(rh_seven_dof_t *m, const rh_vehicle_t *p,
                       const rh_seven_dof_config_t *cfg);

/* xn (3) = state after ctx->ts seconds with DeltaM dm (N m) held; NaN on invalid input. */
void rh_seven_dof_predict(const rh_seven_dof_t *m, const real_t x[3], real_t dm,
                          const rh_ctx_t *ctx, real_t xn[3]);

/* predict + Jacobians in one pass: xn (3), A (3x3 row-major dxn/dx), B (3, dxn/dDeltaM per
 * N m); NaN on invalid input. xn equals rh_seven_dof_predict's up to rounding. */
void rh_seven_dof_predict_linearize(const rh_seven_dof_t *m, const real_t x[3], real_t dm,
                                    const rh_ctx_t *ctx, real_t xn[3], real_t A[9],
                                    real_t B[3]);

/* sizeof(rh_seven_dof_t), bytes (layout checks of bindings). */
size_t rh_seven_dof_sizeof(void);

#endif /* RH_SEVEN_DOF_H */
