/* Grip-limited demand (see grip_demand.h). */
#include "grip_demand.h"

#include <math.h>

#include "grip.h"

void rh_grip_demand_init(rh_grip_demand_t *d, const rh_handling_config_t *h,
                         const rh_vehicle_t *p, double v_min) {
  rh_linear_refs_init(&d->linear, p);
  d->margin = h->demand_margin;
  d->sharpness = h->demand_sharpness;
  d->share = h->fixed_point_share;
  d->beta_lo = h->fixed_point_beta_lo;
  d->beta_hi = h->fixed_point_beta_hi;
  d->v_min = v_min;
  rh_sideslip_guard_init(&d->guard, h->guard_beta_rad, h->guard_gain_per_s, v_min,
                         h->guard_lead_s);
  rh_grip_demand_reset(d);
}

void rh_grip_demand_reset(rh_grip_demand_t *d) {
  d->factor_last = 1.0;
  d->weight_last = 0.0;
  rh_sideslip_guard_reset(&d->guard);
}

static double pymax(double a, double b) { return b > a ? b : a; }
static double pymin(double a, double b) { return b < a ? b : a; }

void rh_grip_demand_compute(rh_grip_demand_t *d, double mu, rh_refs_t *fixed_point,
                            const rh_rhonn_view_t *model, real_t vx, real_t vy,
                            real_t yaw_rate, real_t delta_w, real_t total_torque,
                            real_t ay_meas, real_t out[3]) {
  real_t lin[3];
  double r_lim, f, r_d, vy_d, vxd = (double)vx, den = pymax(vxd, d->v_min);
  rh_linear_refs_compute(&d->linear, vx, vy, yaw_rate, delta_w, total_torque, ay_meas, lin);
  r_lim = d->margin * mu * RH_GRIP_G / den;
  f = 1.0 / pow(1.0 + pow(fabs((double)lin[0] / r_lim), d->sharpness), 1.0 / d->sharpness);
  d->factor_last = f;
  r_d = f * (double)lin[0];
  vy_d = f * (double)lin[2] * vxd;
  if (fixed_point != NULL && d->share > 0.0) {
    real_t fp[3];
    double beta, w;
    rh_refs_compute(fixed_point, model, vx, vy, yaw_rate, delta_w, total_torque, ay_meas, fp);
    beta = isfinite((double)vy + vxd) ? fabs((double)vy) / den : 0.0;
    w = d->share * pymin(pymax((beta - d->beta_lo) / (d->beta_hi - d->beta_lo), 0.0), 1.0);
    d->weight_last = w;
    r_d = (1.0 - w) * r_d + w * (double)fp[0];
    vy_d = (1.0 - w) * vy_d + w * (double)fp[1];
  }
  out[0] = (real_t)r_d;
  out[1] = (real_t)vy_d;
  out[2] = (real_t)(vy_d / den);
  rh_sideslip_guard_apply(&d->guard, vx, vy, yaw_rate, ay_meas, out);
}

void rh_grip_demand_sizes(int out[2]) {
  out[0] = (int)sizeof(rh_grip_demand_t);
  out[1] = (int)sizeof(rh_handling_config_t);
}
