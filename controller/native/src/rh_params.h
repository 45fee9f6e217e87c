/* Vehicle/motor parameters as the controller knows them (controller/config/vehicle.toml)
 * and the per-step prediction context. SI units; wheel order 1 FL, 2 FR, 3 RL, 4 RR. */
#ifndef RH_PARAMS_H
#define RH_PARAMS_H

#include "rh_real.h"

typedef struct {
  double mass_kg;             /* kg */
  double yaw_inertia_kgm2;    /* kg m^2 */
  double lf_m;                /* CG to front axle, m */
  double lr_m;                /* CG to rear axle, m */
  double track_m;             /* wB, m */
  double wheel_inertia_kgm2;  /* kg m^2 */
  double wheel_radius_m;      /* m */
  double cf_axle_n_per_rad;   /* axle cornering stiffness, N/rad (negative) */
  double cr_axle_n_per_rad;   /* N/rad (negative) */
  double cg_height_m;         /* m */
  double steering_ratio;      /* steering-wheel / road-wheel angle, - */
  double peak_torque_nm;      /* per motor, N m */
  double peak_power_w;        /* per motor, W */
  double torque_rate_nm_per_s; /* per motor |dT/dt| the motor follows, N m/s (0 = no limit) */
} rh_vehicle_t;

/* Inputs held over the horizon (Python: interfaces.PredictionContext). */
typedef struct {
  real_t delta_w;         /* road-wheel angle, rad */
  real_t total_torque;    /* Tt, N m */
  real_t ts;              /* model sampling time, s */
  real_t wheel_speeds[4]; /* rad/s */
  real_t delta_m_prev;    /* Delta M applied over the last period, N m */
} rh_ctx_t;

#endif /* RH_PARAMS_H */
