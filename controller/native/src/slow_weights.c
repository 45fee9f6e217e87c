/* Slow weight copy of the references (see slow_weights.h). */
#include "slow_weights.h"

void rh_slow_weights_init(rh_slow_weights_t *s, double tau_s, double ts) {
  int i;
  double tau = tau_s > 0.0 ? tau_s : 0.0;
  for (i = 0; i < RH_NW; i++) s->copy[i] = RH_R(0.0);
  s->tau_s = (real_t)tau;
  s->alpha = (real_t)(tau > 0.0 ? 1.0 - exp(-ts / tau) : 1.0);
  s->started = 0;
}

void rh_slow_weights_reset(rh_slow_weights_t *s) { s->started = 0; }

void rh_slow_weights_set_copy(rh_slow_weights_t *s, const real_t W[RH_NW]) {
  int i;
  for (i = 0; i < RH_NW; i++) s->copy[i] = W[i];
}

void rh_slow_weights_update(rh_slow_weights_t *s, const real_t W[RH_NW]) {
  int i;
  real_t sum = RH_R(0.0);
  if (!(s->tau_s > RH_R(0.0))) return;
  for (i = 0; i < RH_NW; i++) sum += W[i];
  if (!RH_FINITE(sum)) return;
  if (!s->started) {
    for (i = 0; i < RH_NW; i++) s->copy[i] = W[i];
    s->started = 1;
    return;
  }
  for (i = 0; i < RH_NW; i++) s->copy[i] += s->alpha * (W[i] - s->copy[i]);
}

const real_t *rh_slow_weights_W(const rh_slow_weights_t *s, const real_t *live) {
  return s->tau_s > RH_R(0.0) ? s->copy : live;
}

void rh_slow_weights_coefficients(const rh_slow_weights_t *s, const rh_rhonn_view_t *m,
                                  real_t vx, real_t delta_w, real_t C[12]) {
  real_t a = rh_rhonn_xi(m->mu, m->beta, 0, vx);
  real_t d = rh_rhonn_xi(m->mu, m->beta, 3, delta_w);
  rh_rhonn_bilinear(rh_slow_weights_W(s, m->W), a, d, C);
}
