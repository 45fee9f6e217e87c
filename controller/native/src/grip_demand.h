/* The grip-limited yaw demand ([references] kind = "grip"). Python reference:
 * controller/core/references/grip_demand.py (GripDemandReferences), parameters [handling]
 * (controller/core/mpc/envelope.py). Computed in double (the reference's Python floats).
 *
 *   r_lim = demand_margin mu g / max(vx, v_min)
 *   f = 1 / (1 + |r_lin / r_lim|^n)^(1/n);  wrd = f r_lin, Vyd = f beta_lin vx
 *   share w = fixed_point_share clip((|vy|/max(vx, v_min) - beta_lo)/(beta_hi - beta_lo), 0, 1)
 *   of Algorithm 1's output (the caller's rh_refs_t, configured as kind algorithm1);
 *   betad = Vyd / max(vx, v_min); then the sideslip guard (when its gain > 0). */
#ifndef RH_GRIP_DEMAND_H
#define RH_GRIP_DEMAND_H

#include "linear_refs.h"
#include "refs.h"
#include "rh_params.h"
#include "sideslip_guard.h"

/* The [handling] fields the demand and the envelope read (HandlingConfig). */
typedef struct {
  int envelope;              /* envelope rows in the nmpc-rhonn QP (0/1) */
  double yaw_margin;         /* k_r, - */
  double rear_slip_factor;   /* k_alpha, - */
  double lead_s;             /* look-ahead on beta, s */
  double slack_linear;       /* exact penalty per unit slack */
  double slack_quad;         /* quadratic penalty per unit slack^2 */
  double demand_margin;      /* k_d, - */
  double demand_sharpness;   /* n, - */
  double fixed_point_share;  /* largest share of Algorithm 1, - */
  double fixed_point_beta_lo;/* |beta| where the share starts, rad */
  double fixed_point_beta_hi;/* ... and is reached, rad */
  double v_min_mps;          /* no envelope rows below this speed, m/s */
  double guard_beta_rad;     /* [references] sideslip guard around the demand: threshold, rad */
  double guard_gain_per_s;   /*   its gain, 1/s (0 = off) */
  double guard_lead_s;       /*   its look-ahead, s */
} rh_handling_config_t;

typedef struct {
  rh_linear_refs_t linear;
  double margin, sharpness, share, beta_lo, beta_hi, v_min;
  rh_sideslip_guard_t guard;
  double factor_last;        /* wrd / r_lin of the last call, - */
  double weight_last;        /* share of Algorithm 1 in the last call, - */
} rh_grip_demand_t;

/* v_min: [references] v_min, m/s. */
void rh_grip_demand_init(rh_grip_demand_t *d, const rh_handling_config_t *h,
                         const rh_vehicle_t *p, double v_min);
void rh_grip_demand_reset(rh_grip_demand_t *d);
/* out = (wrd rad/s, Vyd m/s, betad rad) at the grip estimate mu (-); fixed_point: Algorithm
 * 1 (kind algorithm1, no guard) or NULL when the share is 0. */
void rh_grip_demand_compute(rh_grip_demand_t *d, double mu, rh_refs_t *fixed_point,
                            const rh_rhonn_view_t *model, real_t vx, real_t vy,
                            real_t yaw_rate, real_t delta_w, real_t total_torque,
                            real_t ay_meas, real_t out[3]);
/* sizeof(rh_grip_demand_t), sizeof(rh_handling_config_t), bytes (layout checks). */
void rh_grip_demand_sizes(int out[2]);

#endif /* RH_GRIP_DEMAND_H */
