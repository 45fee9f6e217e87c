/* The joint filter of the yaw row's weights and theta (see yaw_gain.h; reference
 * controller/core/learning/input_gain.py on ekf.py / ud_ekf.py with one filter of 16
 * weights, whose operation order the two forms below follow as ekf.c and ud_ekf.c do). */
#include "yaw_gain.h"

#include <string.h>

#include "ud_ekf.h"

#define L_ RH_YAW_GAIN_L
#define TH_ RH_YAW_GAIN_THETA

/* P = p0 I (standard) or U = I, D = p0 (UD): the filter's own cold start and trace reset. */
static void cold_covariance(rh_yaw_gain_t *g) {
  int a;
  for (a = 0; a < RH_YAW_GAIN_LL; a++) g->PU[a] = RH_R(0.0);
  for (a = 0; a < L_; a++) {
    if (g->ud) {
      g->PU[a * L_ + a] = RH_R(1.0);
      g->D[a] = g->p0;
    } else {
      g->PU[a * L_ + a] = g->p0;
      g->D[a] = RH_R(0.0);
    }
  }
}

int rh_yaw_gain_init(rh_yaw_gain_t *g, const rh_yaw_gain_config_t *cfg,
                     const rh_ekf_config_t *ekf, int ud, const real_t w_r0[RH_NPHI]) {
  int a;
  int rc = -1;
  (void)memset(g, 0, sizeof(*g));
  if ((cfg->dm_gain_p0 > 0.0) && isfinite(cfg->dm_gain_p0) && (0.0 < cfg->dm_gain_min) &&
      (cfg->dm_gain_min <= 1.0) && (1.0 <= cfg->dm_gain_max)) {
    for (a = 0; a < RH_NPHI; a++) {
      g->w0[a] = w_r0[a];
    }
    g->w0[TH_] = RH_R(1.0);
    g->r = (real_t)ekf->r[2];
    g->zeta = (real_t)ekf->zeta[2];
    g->q = (real_t)ekf->q;
    g->p_floor = (real_t)ekf->p_floor;
    g->trace_max = (real_t)ekf->trace_max;
    g->p0 = (real_t)ekf->p0;
    g->w_max = (real_t)ekf->w_max;
    g->theta_p0 = (real_t)cfg->dm_gain_p0;
    g->theta_min = (real_t)cfg->dm_gain_min;
    g->theta_max = (real_t)cfg->dm_gain_max;
    if (ud != 0) g->ud = 1;
    g->eig_check_every = ekf->eig_check_every;
    rh_yaw_gain_reset(g);
    rc = 0;
  }
  return rc;
}

void rh_yaw_gain_reset(rh_yaw_gain_t *g) {
  int a;
  for (a = 0; a < L_; a++) g->W[a] = g->w0[a];
  cold_covariance(g);
  /* theta's own prior: its row and column of P (of U) cleared, its variance theta_p0 */
  if (g->ud) {
    g->D[TH_] = g->theta_p0;
  } else {
    g->PU[TH_ * L_ + TH_] = g->theta_p0;
  }
  (void)memset(&g->counters, 0, sizeof(g->counters));
  g->since_eig = 0;
}

/* Standard form (ekf.c's per-row update on 16 weights); h finite, returns 0 on a bad s. */
static int update_standard(rh_yaw_gain_t *g, const real_t h[L_], real_t e) {
  real_t ph[L_]; /* P h, then v = P h / sqrt(s) */
  real_t *P = g->PU;
  real_t s = RH_R(0.0), ze, rs, tr = RH_R(0.0);
  int a, b;
  for (a = 0; a < L_; a++) {
    real_t acc = RH_R(0.0);
    for (b = 0; b < L_; b++) acc += P[a * L_ + b] * h[b];
    ph[a] = acc;
  }
  for (a = 0; a < L_; a++) s += ph[a] * h[a];
  s = s + g->r;
  if (!(RH_FINITE(s) && s > RH_R(0.0))) return 0;
  ze = g->zeta * e;
  rs = RH_SQRT(s);
  for (a = 0; a < L_; a++) g->W[a] += (ph[a] / s) * ze;
  for (a = 0; a < L_; a++) ph[a] = ph[a] / rs;
  for (a = 0; a < L_; a++) {
    real_t va = ph[a];
    for (b = 0; b < L_; b++) P[a * L_ + b] -= va * ph[b];
  }
  for (a = 0; a < L_; a++) P[a * L_ + a] += g->q;
  for (a = 0; a < L_; a++) {
    if (P[a * L_ + a] < g->p_floor) P[a * L_ + a] = g->p_floor;
    tr += P[a * L_ + a];
  }
  if (tr > g->trace_max) {
    cold_covariance(g);
    g->counters.trace_resets += 1;
  }
  return 1;
}

/* UD form (ud_ekf.c's per-row update on 16 weights); h finite, returns 0 on a bad s. */
static int update_ud(rh_yaw_gain_t *g, const real_t h[L_], real_t e) {
  real_t k[L_];  /* unnormalised gain */
  real_t fv[L_]; /* U' h (measurement), then the rank-one vector (time update), - */
  real_t *U = g->PU, *D = g->D;
  real_t s = g->r, alpha, ze, tr = RH_R(0.0);
  int j, a;
  for (j = 0; j < L_; j++) {
    real_t fj = RH_R(0.0);
    for (a = 0; a <= j; a++) fj += U[a * L_ + j] * h[a];
    fv[j] = fj;
    s += D[j] * fj * fj;
  }
  if (!(RH_FINITE(s) && s > RH_R(0.0))) return 0;
  /* Bierman: sequential scalar update of U, D and the gain k. */
  alpha = g->r;
  for (j = 0; j < L_; j++) {
    real_t vj = D[j] * fv[j];
    real_t beta = alpha;
    real_t lam;
    alpha = alpha + fv[j] * vj;
    lam = -fv[j] / beta;
    D[j] = D[j] * (beta / alpha);
    for (a = 0; a < j; a++) {
      real_t tmp = U[a * L_ + j];
      U[a * L_ + j] = tmp + lam * k[a];
      k[a] = k[a] + vj * tmp;
    }
    k[j] = vj;
  }
  ze = g->zeta * e;
  for (a = 0; a < L_; a++) g->W[a] += (k[a] / alpha) * ze;
  rh_ud_add_scaled_identity(U, D, L_, 0, g->q, fv); /* time update P <- P + q I */
  for (j = 0; j < L_; j++) {
    real_t col = RH_R(0.0);
    if (D[j] < g->p_floor) D[j] = g->p_floor;
    for (a = 0; a <= j; a++) col += U[a * L_ + j] * U[a * L_ + j];
    tr += D[j] * col;
  }
  if (tr > g->trace_max) {
    cold_covariance(g);
    g->counters.trace_resets += 1;
  }
  return 1;
}

int rh_yaw_gain_update(rh_yaw_gain_t *g, const real_t phi[RH_NPHI], real_t u, real_t e_r) {
  real_t h[L_]; /* regressor [phi, u] */
  real_t sh = RH_R(0.0), th;
  int a, clipped = 0;
  for (a = 0; a < RH_NPHI; a++) h[a] = phi[a];
  h[TH_] = u;
  for (a = 0; a < L_; a++) sh += h[a];
  if (!(RH_FINITE(sh) && RH_FINITE(e_r)) ||
      !(g->ud ? update_ud(g, h, e_r) : update_standard(g, h, e_r))) {
    g->counters.rejected += 1;
    return 0;
  }
  for (a = 0; a < L_; a++) {
    if (g->W[a] > g->w_max) {
      g->W[a] = g->w_max;
      clipped = 1;
    } else if (g->W[a] < -g->w_max) {
      g->W[a] = -g->w_max;
      clipped = 1;
    }
  }
  if (clipped) g->counters.weight_clips += 1;
  g->counters.updates += 1;
  if (!g->ud && g->eig_check_every > 0) {
    g->since_eig += 1;
    if (g->since_eig >= g->eig_check_every) {
      g->since_eig = 0;
      g->counters.eig_repairs += rh_ekf_floor_spd(g->PU, L_, g->p_floor, g->p0);
    }
  }
  th = g->W[TH_];
  th = th < g->theta_min ? g->theta_min : th;
  g->W[TH_] = th > g->theta_max ? g->theta_max : th;
  return 1;
}

int rh_yaw_gain_size(void) { return (int)sizeof(rh_yaw_gain_t); }
