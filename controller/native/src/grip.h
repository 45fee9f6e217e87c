/* Available road friction from bus signals (Python reference: controller/core/grip.py,
 * GripEstimator). Computed in double in both precisions (the reference's Python floats).
 *
 * a = |(ax, ay)| / g, the grip in use; e = peak hold of a decaying with hold_tau_s; the
 * saturation index s = clip((x - lo)/(hi - lo), 0, 1) of the slip x (rad) each axle needs
 * beyond the linear law alpha_lin = -k ay (k = m l_other / (L |C_axle|)), the larger axle;
 * target = (1 - s) clip(shown_factor e, mu_floor, mu_max) + s a;
 * mu <- mu + min(ts / tau_s, 1) (target - mu), then max(mu, a, RH_GRIP_MU_LOWEST), <= mu_max.
 * Held below v_min_mps, for non-finite inputs and an implausible grip in use. */
#ifndef RH_GRIP_H
#define RH_GRIP_H

#include "rh_params.h"

#define RH_GRIP_G 9.81          /* m/s^2 */
#define RH_GRIP_MU_LOWEST 0.05  /* the estimate never goes below this, - */
#define RH_GRIP_IMPLAUSIBLE 3.0 /* a grip in use above this (3 g) is a fault: held, - */

/* GripConfig ([grip]); field order = the dataclass's. */
typedef struct {
  double mu_max;             /* highest estimate, - */
  double mu_floor;           /* a road that has shown no grip yet, - */
  double shown_factor;       /* credit on the grip shown, - */
  double hold_tau_s;         /* decay of the grip shown, s */
  double tau_s;              /* time constant of the estimate, s */
  double slip_excess_lo_rad; /* slip beyond the linear law where saturation starts, rad */
  double slip_excess_hi_rad; /* ... and is complete, rad */
  double v_min_mps;          /* no update below this speed, m/s */
} rh_grip_config_t;

typedef struct {
  rh_grip_config_t cfg;
  double lf, lr;             /* m */
  double k_front, k_rear;    /* linear slip per lateral acceleration, rad/(m/s^2) */
  double hold;               /* peak-hold decay per update, - */
  double gain;               /* estimate update gain, - */
  double mu;                 /* the estimate, - */
  double shown;              /* grip shown, - */
  double saturation;         /* last saturation index, - */
  double grip_used;          /* last grip in use, - */
} rh_grip_t;

/* ts_s: update period, s. */
void rh_grip_init(rh_grip_t *g, const rh_grip_config_t *cfg, const rh_vehicle_t *p, double ts_s);
void rh_grip_reset(rh_grip_t *g);
/* One period; vx, vy m/s, yaw rate rad/s, road-wheel angle rad, ax, ay m/s^2. Returns mu. */
double rh_grip_update(rh_grip_t *g, double vx, double vy, double yaw_rate, double delta_w,
                      double ax, double ay);
/* sizeof(rh_grip_t), sizeof(rh_grip_config_t), bytes (layout checks of bindings). */
void rh_grip_sizes(int out[2]);

#endif /* RH_GRIP_H */
