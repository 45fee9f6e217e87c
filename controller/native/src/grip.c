/* Grip estimate (see grip.h). */
#include "grip.h"

#include <math.h>

void rh_grip_init(rh_grip_t *g, const rh_grip_config_t *cfg, const rh_vehicle_t *p,
                  double ts_s) {
  double L = p->lf_m + p->lr_m;
  g->cfg = *cfg;
  g->lf = p->lf_m;
  g->lr = p->lr_m;
  g->k_front = p->mass_kg * p->lr_m / (L * fabs(p->cf_axle_n_per_rad));
  g->k_rear = p->mass_kg * p->lf_m / (L * fabs(p->cr_axle_n_per_rad));
  g->hold = exp(-ts_s / cfg->hold_tau_s);
  g->gain = ts_s / cfg->tau_s < 1.0 ? ts_s / cfg->tau_s : 1.0;
  rh_grip_reset(g);
}

void rh_grip_reset(rh_grip_t *g) {
  g->mu = g->cfg.mu_floor;
  g->shown = 0.0;
  g->saturation = 0.0;
  g->grip_used = 0.0;
}

static double pymax(double a, double b) { return b > a ? b : a; }
static double pymin(double a, double b) { return b < a ? b : a; }

double rh_grip_update(rh_grip_t *g, double vx, double vy, double yaw_rate, double delta_w,
                      double ax, double ay) {
  const rh_grip_config_t *c = &g->cfg;
  double a, a_r, a_f, e, s, credit, target, mu;
  if (!(isfinite(vx + vy + yaw_rate + delta_w + ax + ay) && vx >= c->v_min_mps)) return g->mu;
  a = sqrt(ax * ax + ay * ay) / RH_GRIP_G;
  a_r = (vy - g->lr * yaw_rate) / vx;
  a_f = (vy + g->lf * yaw_rate) / vx - delta_w;
  e = pymax(fabs(a_r + g->k_rear * ay), fabs(a_f + g->k_front * ay));
  if (!(a <= RH_GRIP_IMPLAUSIBLE && isfinite(e))) return g->mu; /* sensor fault, overflow */
  s = pymin(pymax((e - c->slip_excess_lo_rad) / (c->slip_excess_hi_rad - c->slip_excess_lo_rad),
                  0.0), 1.0);
  g->shown = pymax(a, g->shown * g->hold);
  credit = pymin(pymax(c->shown_factor * g->shown, c->mu_floor), c->mu_max);
  target = (1.0 - s) * credit + s * a;
  mu = g->mu + g->gain * (target - g->mu);
  g->mu = pymin(pymax(pymax(mu, a), RH_GRIP_MU_LOWEST), c->mu_max);
  g->saturation = s;
  g->grip_used = a;
  return g->mu;
}

void rh_grip_sizes(int out[2]) {
  out[0] = (int)sizeof(rh_grip_t);
  out[1] = (int)sizeof(rh_grip_config_t);
}
