/* Sideslip guard on any yaw-rate reference. Python reference:
 * controller/core/references/sideslip_guard.py (SideslipGuard.compute).
 * While |beta| = |Vy/Vx| exceeds beta_rad by e, wrd is held where beta shrinks at least at
 * k e:  sgn(beta) wrd >= sgn(beta) ay/Vx + k e  (beta_dot ~ ay/Vx - wr; k = gain_per_s).
 * Look-ahead (lead_s = T > 0, and a finite measured wr): the guard acts on
 * beta_T = beta + T (ay/Vx - wr) instead of beta. */
#ifndef RH_SIDESLIP_GUARD_H
#define RH_SIDESLIP_GUARD_H

#include "rh_real.h"

typedef struct {
  real_t beta_rad;   /* |beta| threshold, rad */
  real_t gain_per_s; /* demanded decay rate of the excess, 1/s */
  real_t v_min;      /* no guard at Vx <= v_min, m/s */
  real_t lead_s;     /* look-ahead T on beta_dot, s (<= 0: on beta alone) */
  int enabled;       /* 1 when gain_per_s > 0 (factory.make_rhonn_references) */
  int active_calls;  /* calls since reset in which the guard changed wrd */
} rh_sideslip_guard_t;

/* beta_rad rad, gain_per_s 1/s (<= 0: disabled), v_min m/s, lead_s s (<= 0: off). */
void rh_sideslip_guard_init(rh_sideslip_guard_t *g, double beta_rad, double gain_per_s,
                            double v_min, double lead_s);
void rh_sideslip_guard_reset(rh_sideslip_guard_t *g);

/* Limit out[0] (wrd rad/s) in place for Vx m/s, measured Vy m/s, measured yaw rate wr rad/s
 * (read only with lead_s > 0) and ay m/s^2; out[1], out[2] unchanged. Returns 1 if wrd was
 * changed (counted), else 0 (also when disabled). */
int rh_sideslip_guard_apply(rh_sideslip_guard_t *g, real_t vx, real_t vy, real_t yaw_rate,
                            real_t ay_meas, real_t out[3]);

#endif /* RH_SIDESLIP_GUARD_H */
