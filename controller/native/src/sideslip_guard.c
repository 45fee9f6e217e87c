/* Sideslip guard (see sideslip_guard.h). */
#include "sideslip_guard.h"

void rh_sideslip_guard_init(rh_sideslip_guard_t *g, double beta_rad, double gain_per_s,
                            double v_min, double lead_s) {
  g->beta_rad = (real_t)beta_rad;
  g->gain_per_s = (real_t)gain_per_s;
  g->v_min = (real_t)v_min;
  g->lead_s = (real_t)lead_s;
  g->enabled = gain_per_s > 0.0;
  g->active_calls = 0;
}

void rh_sideslip_guard_reset(rh_sideslip_guard_t *g) { g->active_calls = 0; }

int rh_sideslip_guard_apply(rh_sideslip_guard_t *g, real_t vx, real_t vy, real_t yaw_rate,
                            real_t ay_meas, real_t out[3]) {
  real_t beta, excess, s, r_lim;
  if (!g->enabled) return 0;
  if (!(vx > g->v_min && RH_FINITE(vy) && RH_FINITE(ay_meas))) return 0;
  beta = vy / vx;                        /* rad */
  if (g->lead_s > RH_R(0.0) && RH_FINITE(yaw_rate))
    beta += g->lead_s * (ay_meas / vx - yaw_rate); /* beta T s ahead, rad */
  excess = RH_FABS(beta) - g->beta_rad;  /* rad */
  if (excess <= RH_R(0.0)) return 0;
  s = beta > RH_R(0.0) ? RH_R(1.0) : RH_R(-1.0);
  r_lim = ay_meas / vx + s * g->gain_per_s * excess; /* rad/s */
  if (s * out[0] < s * r_lim) {
    out[0] = r_lim;
    g->active_calls += 1;
    return 1;
  }
  return 0;
}
