/* Driver-intent, bicycle-demand references and the blend weight (see refs_intent.h). */
#include "refs_intent.h"

#define DEN_MIN 0.5                      /* floor on 1 + K vx^2, - (linear.py) */
#define MAX_SPEED_MPS 1000.0             /* |vx| above: invalid input, m/s */
#define MAX_STEER_RAD 1.5707963267948966 /* |dw| above (pi/2): invalid input, rad */

static int check_times(const rh_refs_config_t *cfg) {
  return (cfg->ts > 0.0 && cfg->ay_decay_s > 0.0) ? RH_REFS_OK : RH_REFS_ETIME;
}

int rh_refs_intent_init(rh_refs_intent_t *s, const rh_refs_config_t *cfg,
                        const rh_vehicle_t *p) {
  int e = check_times(cfg);
  if (e != RH_REFS_OK) return e;
  s->ts = (real_t)cfg->ts;
  s->v_min = (real_t)cfg->v_min;
  s->intent_lead_s = (real_t)cfg->intent_lead_s;
  s->intent_ay_margin = (real_t)cfg->intent_ay_margin;
  s->ay_floor = (real_t)cfg->ay_floor;
  s->ay_ceiling = (real_t)cfg->ay_ceiling;
  s->r_kin_factor = (real_t)cfg->r_kin_factor;
  s->r_band = (real_t)cfg->r_band;
  s->tan_beta_max = (real_t)cfg->tan_beta_max;
  s->decay = (real_t)exp(-cfg->ts / cfg->ay_decay_s);
  s->wheelbase_m = (real_t)(p->lf_m + p->lr_m);
  s->lr_m = (real_t)p->lr_m;
  rh_slow_weights_init(&s->weights, cfg->slow_tau_s, cfg->ts);
  rh_refs_intent_reset(s);
  return RH_REFS_OK;
}

void rh_refs_intent_reset(rh_refs_intent_t *s) {
  rh_slow_weights_reset(&s->weights);
  s->ay_envelope = RH_R(0.0);
  s->fallbacks = 0;
  s->gain_last = RH_R(0.0);
  s->dw_prev = (real_t)NAN;
}

/* S_j^-1(xi) = atanh(clip(xi/mu_j, +-0.995)) / beta_j, state units. */
static real_t inverse_s(const rh_rhonn_view_t *m, int j, real_t xi) {
  real_t u = rh_refs_pymin(rh_refs_pymax(xi / m->mu[j], -RH_R(RH_REFS_XI_CLIP)),
                           RH_R(RH_REFS_XI_CLIP));
  return RH_ATANH(u) / m->beta[j];
}

int rh_refs_intent_steady_response(const rh_refs_intent_t *s, const rh_rhonn_view_t *m,
                                   real_t vx, real_t delta_w, real_t *vy_d, real_t *r_d) {
  real_t c[12], cz[12];
  real_t rhs_v, rhs_r, a11, a12, a21, a22, det, xi_v, xi_r;
  rh_slow_weights_coefficients(&s->weights, m, vx, delta_w, c);
  rh_slow_weights_coefficients(&s->weights, m, vx, RH_R(0.0), cz);
  rhs_v = -(c[4] - cz[4]);
  rhs_r = -(c[8] - cz[8]);
  a11 = c[5];
  a12 = c[6];
  a21 = c[9];
  a22 = c[10];
  if (!m->increment) {
    a11 -= RH_R(1.0);
    a22 -= RH_R(1.0);
  }
  det = a11 * a22 - a12 * a21;
  if (!(RH_FINITE(det) && det > RH_R(1e-9) && a11 + a22 < RH_R(0.0))) return 0;
  xi_v = (a22 * rhs_v - a12 * rhs_r) / det;
  xi_r = (a11 * rhs_r - a21 * rhs_v) / det;
  if (!(RH_FINITE(xi_v) && RH_FINITE(xi_r))) return 0;
  *vy_d = inverse_s(m, 1, xi_v);
  *r_d = inverse_s(m, 2, xi_r);
  return 1;
}

void rh_refs_intent_compute(rh_refs_intent_t *s, const rh_rhonn_view_t *m, real_t vx,
                            real_t delta_w, real_t ay_meas, real_t out[3]) {
  real_t dw_rate, r_neutral, vy_d, r_d, r_kin, v_lim;
  rh_slow_weights_update(&s->weights, m->W);
  if (RH_FINITE(ay_meas))
    s->ay_envelope = rh_refs_pymax(RH_FABS(ay_meas), s->ay_envelope * s->decay);
  if (!(RH_FINITE(vx) && RH_FINITE(delta_w))) {
    out[0] = RH_R(0.0); out[1] = RH_R(0.0); out[2] = RH_R(0.0);
    return;
  }
  dw_rate = isnan(s->dw_prev) ? RH_R(0.0) : (delta_w - s->dw_prev) / s->ts; /* rad/s */
  s->dw_prev = delta_w;
  r_neutral = rh_refs_pymax(vx, RH_R(0.0)) * delta_w / s->wheelbase_m; /* rad/s */
  if (vx < s->v_min) {
    vy_d = s->lr_m * r_neutral;
    out[0] = r_neutral;
    out[1] = vy_d;
    out[2] = vy_d / s->v_min;
    return;
  }
  if (!rh_refs_intent_steady_response(s, m, vx, delta_w, &vy_d, &r_d)) {
    s->fallbacks += 1;
    vy_d = s->lr_m * r_neutral;
    r_d = r_neutral;
  }
  if (RH_FABS(delta_w) > RH_R(1e-4)) s->gain_last = r_d / delta_w;
  if (s->intent_lead_s > RH_R(0.0)) r_d += s->intent_lead_s * s->gain_last * dw_rate;
  r_kin = s->r_kin_factor * r_neutral;
  r_d = rh_refs_pymin(rh_refs_pymax(r_d, rh_refs_pymin(r_kin, RH_R(0.0)) - s->r_band),
                      rh_refs_pymax(r_kin, RH_R(0.0)) + s->r_band);
  if (s->intent_ay_margin > RH_R(0.0)) {
    real_t a_max = rh_refs_pymin(
        rh_refs_pymax(s->intent_ay_margin * s->ay_envelope, s->ay_floor), s->ay_ceiling);
    r_d = rh_refs_pymin(rh_refs_pymax(r_d, -a_max / vx), a_max / vx);
  }
  v_lim = s->tan_beta_max * vx;
  vy_d = rh_refs_pymin(rh_refs_pymax(vy_d, -v_lim), v_lim);
  out[0] = r_d;
  out[1] = vy_d;
  out[2] = vy_d / vx;
}

int rh_refs_bicycle_init(rh_refs_bicycle_t *s, const rh_refs_config_t *cfg,
                         const rh_vehicle_t *p) {
  double cf = fabs(p->cf_axle_n_per_rad), cr = fabs(p->cr_axle_n_per_rad);
  double L = p->lf_m + p->lr_m;
  int e = check_times(cfg);
  if (e != RH_REFS_OK) return e;
  s->ts = (real_t)cfg->ts;
  s->v_min = (real_t)cfg->v_min;
  s->intent_lead_s = (real_t)cfg->intent_lead_s;
  s->intent_ay_margin = (real_t)cfg->intent_ay_margin;
  s->ay_floor = (real_t)cfg->ay_floor;
  s->ay_ceiling = (real_t)cfg->ay_ceiling;
  s->decay = (real_t)exp(-cfg->ts / cfg->ay_decay_s);
  s->understeer_gradient = (real_t)(p->mass_kg / (L * L) * (p->lr_m / cf - p->lf_m / cr));
  s->wheelbase_m = (real_t)L;
  s->lr_m = (real_t)p->lr_m;
  s->beta_k = (real_t)(p->mass_kg * p->lf_m / (L * cr));
  rh_refs_bicycle_reset(s);
  return RH_REFS_OK;
}

void rh_refs_bicycle_reset(rh_refs_bicycle_t *s) {
  s->ay_envelope = RH_R(0.0);
  s->dw_prev = (real_t)NAN;
}

void rh_refs_bicycle_compute(rh_refs_bicycle_t *s, real_t vx, real_t delta_w, real_t ay_meas,
                             real_t out[3]) {
  real_t r_d, vy_d, b_d, rate;
  if (RH_FINITE(ay_meas))
    s->ay_envelope = rh_refs_pymax(RH_FABS(ay_meas), s->ay_envelope * s->decay);
  /* LinearReferences.compute: 2-DoF bicycle steady state (NaN fails the range test) */
  if (!(RH_FABS(vx) <= RH_R(MAX_SPEED_MPS) && RH_FABS(delta_w) <= RH_R(MAX_STEER_RAD))) {
    r_d = RH_R(0.0); vy_d = RH_R(0.0); b_d = RH_R(0.0);
  } else {
    real_t v2 = vx * vx;
    real_t den = RH_R(1.0) + s->understeer_gradient * v2;
    if (den < RH_R(DEN_MIN)) den = RH_R(DEN_MIN);
    r_d = vx * delta_w / (s->wheelbase_m * den);
    b_d = delta_w * (s->lr_m - s->beta_k * v2) / (s->wheelbase_m * den);
    vy_d = b_d * vx;
  }
  if (RH_FINITE(delta_w)) {
    rate = isnan(s->dw_prev) ? RH_R(0.0) : (delta_w - s->dw_prev) / s->ts; /* rad/s */
    s->dw_prev = delta_w;
    if (s->intent_lead_s > RH_R(0.0) && RH_FABS(delta_w) > RH_R(1e-5))
      r_d += s->intent_lead_s * (r_d / delta_w) * rate;
    if (s->intent_ay_margin > RH_R(0.0) && vx > s->v_min) {
      real_t a_max = rh_refs_pymin(
          rh_refs_pymax(s->intent_ay_margin * s->ay_envelope, s->ay_floor), s->ay_ceiling);
      r_d = rh_refs_pymin(rh_refs_pymax(r_d, -a_max / vx), a_max / vx);
    }
  }
  out[0] = r_d;
  out[1] = vy_d;
  out[2] = b_d;
}

real_t rh_refs_blend_weight(real_t vx, real_t vy, real_t v_min, real_t beta_lo, real_t span) {
  real_t beta = (RH_FINITE(vy) && RH_FINITE(vx)) ? RH_FABS(vy) / rh_refs_pymax(vx, v_min)
                                                 : RH_R(0.0);
  return rh_refs_pymin(rh_refs_pymax((beta - beta_lo) / span, RH_R(0.0)), RH_R(1.0));
}
