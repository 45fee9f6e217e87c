/* Linear steady-state references of the baselines LMPC and NMPC-MF (paper Section IV-B).
 * Python reference: controller/core/references/linear.py (LinearReferences).
 *
 * 2-DoF bicycle steady state at speed vx (m/s) and road-wheel angle delta (rad), with
 * positive axle stiffnesses |Cf|, |Cr| (N/rad), L = lf + lr (m):
 *   K      = m/L^2 (lr/|Cf| - lf/|Cr|)                     understeer gradient, s^2/m^2
 *   r_ss   = vx delta / (L max(1 + K vx^2, DEN_MIN))         rad/s
 *   beta_ss = delta (lr - m lf vx^2/(L |Cr|)) / (L max(1 + K vx^2, DEN_MIN))   rad
 *   vy_ref = beta_ss vx                                      m/s
 * No road friction (deliberately, as the paper's baselines). Invalid input (non-finite,
 * |vx| > 1000 m/s or |delta| > pi/2) gives (0, 0, 0). The references keep no state. */
#ifndef RH_LINEAR_REFS_H
#define RH_LINEAR_REFS_H

#include <stddef.h>

#include "rh_params.h"
#include "rh_real.h"

#define RH_LINEAR_REFS_DEN_MIN 0.5          /* floor on 1 + K vx^2, - */
#define RH_LINEAR_REFS_MAX_SPEED_MPS 1000.0 /* |vx| above this is invalid input, m/s */

typedef struct {
  double critical_speed_mps; /* 1/sqrt(-K), m/s (HUGE_VAL if K >= 0); informational */
  double guard_speed_mps;    /* speed above which DEN_MIN acts, m/s (HUGE_VAL if K >= 0) */
  real_t wheelbase;          /* L, m */
  real_t understeer_gradient;/* K, s^2/m^2 (< 0: oversteering) */
  real_t lr;                 /* CG to rear axle, m */
  real_t beta_k;             /* m lf / (L |Cr|), s^2/m */
} rh_linear_refs_t;

void rh_linear_refs_init(rh_linear_refs_t *s, const rh_vehicle_t *p);

/* No state to reset (the references are a pure function of vx and delta); kept so that all
 * reference generators share one interface. */
void rh_linear_refs_reset(rh_linear_refs_t *s);

/* out = (yaw_rate_ref rad/s, vy_ref m/s, beta_ref rad). Only vx (m/s) and delta_w (rad) are
 * used; vy (m/s), yaw_rate (rad/s), total_torque (N m), ay_meas (m/s^2) are ignored. */
void rh_linear_refs_compute(const rh_linear_refs_t *s, real_t vx, real_t vy, real_t yaw_rate,
                            real_t delta_w, real_t total_torque, real_t ay_meas,
                            real_t out[3]);

/* sizeof(rh_linear_refs_t), bytes (layout checks of bindings). */
size_t rh_linear_refs_sizeof(void);

#endif /* RH_LINEAR_REFS_H */
