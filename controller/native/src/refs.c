/* Reference dispatcher over the configured kind + sideslip guard (see refs.h). */
#include "refs.h"

#include <string.h>

int rh_refs_init(rh_refs_t *r, const rh_refs_config_t *cfg, const rh_vehicle_t *p) {
  int e = RH_REFS_OK;
  (void)memset(r, 0, sizeof(*r));
  r->kind = cfg->kind;
  r->v_min = (real_t)cfg->v_min;
  r->blend_beta_lo = (real_t)cfg->blend_beta_lo;
  r->blend_span = (real_t)(cfg->blend_beta_hi - cfg->blend_beta_lo > 1e-6
                               ? cfg->blend_beta_hi - cfg->blend_beta_lo
                               : 1e-6);
  switch (cfg->kind) {
    case RH_REFS_ALGORITHM1:
      e = rh_refs_alg1_init(&r->alg1, cfg, p);
      break;
    case RH_REFS_INTENT:
      e = rh_refs_intent_init(&r->intent, cfg, p);
      break;
    case RH_REFS_BLEND:
      e = rh_refs_intent_init(&r->intent, cfg, p);
      if (e == RH_REFS_OK) e = rh_refs_alg1_init(&r->alg1, cfg, p);
      break;
    case RH_REFS_DEMAND:
      e = rh_refs_bicycle_init(&r->demand, cfg, p);
      if (e == RH_REFS_OK) e = rh_refs_alg1_init(&r->alg1, cfg, p);
      break;
    default:
      e = RH_REFS_EKIND;
      break;
  }
  rh_sideslip_guard_init(&r->guard, cfg->guard_beta_rad, cfg->guard_gain_per_s, cfg->v_min,
                         cfg->guard_lead_s);
  r->status = e;
  return e;
}

void rh_refs_reset(rh_refs_t *r) {
  if (r->status != RH_REFS_OK) return;
  if (r->kind != RH_REFS_INTENT) rh_refs_alg1_reset(&r->alg1);
  if (r->kind == RH_REFS_INTENT || r->kind == RH_REFS_BLEND) rh_refs_intent_reset(&r->intent);
  if (r->kind == RH_REFS_DEMAND) rh_refs_bicycle_reset(&r->demand);
  r->weight_last = RH_R(0.0);
  rh_sideslip_guard_reset(&r->guard);
}

void rh_refs_set_slow_weights(rh_refs_t *r, const real_t W[RH_NW]) {
  rh_slow_weights_set_copy(&r->alg1.weights, W);
  rh_slow_weights_set_copy(&r->intent.weights, W);
}

void rh_refs_compute(rh_refs_t *r, const rh_rhonn_view_t *model, real_t vx, real_t vy,
                     real_t yaw_rate, real_t delta_w, real_t total_torque, real_t ay_meas,
                     real_t out[3]) {
  real_t d[3], f[3], w;
  (void)total_torque; /* the steady states hold Vx (dM = 0): Tt is not used */
  if (r->status != RH_REFS_OK) {
    out[0] = RH_R(0.0); out[1] = RH_R(0.0); out[2] = RH_R(0.0);
    return;
  }
  switch (r->kind) {
    case RH_REFS_ALGORITHM1:
      rh_refs_alg1_compute(&r->alg1, model, vx, vy, yaw_rate, delta_w, ay_meas, out);
      break;
    case RH_REFS_INTENT:
      rh_refs_intent_compute(&r->intent, model, vx, delta_w, ay_meas, out);
      break;
    default: /* blend / demand: both parts run every call, mixed by the measured |beta| */
      if (r->kind == RH_REFS_BLEND)
        rh_refs_intent_compute(&r->intent, model, vx, delta_w, ay_meas, d);
      else
        rh_refs_bicycle_compute(&r->demand, vx, delta_w, ay_meas, d);
      rh_refs_alg1_compute(&r->alg1, model, vx, vy, yaw_rate, delta_w, ay_meas, f);
      w = rh_refs_blend_weight(vx, vy, r->v_min, r->blend_beta_lo, r->blend_span);
      r->weight_last = w;
      out[0] = (RH_R(1.0) - w) * d[0] + w * f[0];
      out[1] = (RH_R(1.0) - w) * d[1] + w * f[1];
      out[2] = out[1] / rh_refs_pymax(vx, r->v_min);
      break;
  }
  rh_sideslip_guard_apply(&r->guard, vx, vy, yaw_rate, ay_meas, out);
}

unsigned long rh_refs_sizeof_state(void) { return (unsigned long)sizeof(rh_refs_t); }
unsigned long rh_refs_sizeof_config(void) { return (unsigned long)sizeof(rh_refs_config_t); }
