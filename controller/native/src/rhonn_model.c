/* RHONN prediction model with online EKF learning (see rhonn_model.h). */
#include "rhonn_model.h"

#include <string.h>

/* Index into phi_ext = [1, phi_1..phi_15, 0] of d phi_k / d xi_j for j = Vx, Vy, wr
 * (16: zero). Paper order of rhonn.h. */
static const unsigned char DERIV[3][RH_NPHI] = {
    {0, 16, 16, 16, 2, 3, 4, 16, 16, 16, 8, 9, 10, 16, 14},
    {16, 0, 16, 16, 1, 16, 16, 3, 4, 16, 6, 7, 16, 10, 13},
    {16, 16, 0, 16, 16, 1, 16, 2, 16, 4, 5, 16, 7, 9, 12},
};

int rh_rhonn_model_init(rh_rhonn_model_t *m, const rh_rhonn_config_t *cfg,
                        const rh_vehicle_t *p, double ts_s, const real_t w0[RH_NW]) {
  double td, k_tt, k_dm;
  int j;
  (void)memset(m, 0, sizeof *m);
  if (!(ts_s > 0.0) || (cfg->ekf_form != RH_EKF_STANDARD && cfg->ekf_form != RH_EKF_UD))
    return -1;
  for (j = 0; j < RH_NXI; j++) {
    m->mu[j] = (real_t)cfg->mu[j];
    m->beta[j] = (real_t)cfg->beta[j];
  }
  m->increment = cfg->increment ? 1 : 0;
  k_tt = 1.0 / (p->mass_kg * p->wheel_radius_m);
  k_dm = p->track_m / (2.0 * p->yaw_inertia_kgm2 * p->wheel_radius_m);
  td = cfg->dm_dead_time_s;
  td = td < 0.0 ? 0.0 : (td > ts_s ? ts_s : td);
  m->kd0_now = (real_t)((ts_s - td) * k_dm);
  m->kd0_prev = (real_t)(td * k_dm);
  m->kt_ts = (real_t)(ts_s * k_tt);
  m->gate_on = cfg->gate_err_hi > 0.0;
  m->gate_a = (real_t)(cfg->gate_tau_s > 0.0 ? exp(-ts_s / cfg->gate_tau_s) : 0.0);
  {
    double n = cfg->gate_warmup_s / ts_s;
    /* Python round(): half to even */
    double fl = floor(n), fr = n - fl;
    int64_t r = (int64_t)fl;
    if (fr > 0.5 || (fr == 0.5 && (r % 2) != 0)) r += 1;
    m->gate_n = r > 0 ? r : 0;
  }
  m->gate_err_lo = (real_t)cfg->gate_err_lo;
  m->gate_err_hi = (real_t)cfg->gate_err_hi;
  m->ekf_form = cfg->ekf_form;
  if (cfg->ekf_form == RH_EKF_UD)
    rh_ud_ekf_init(&m->f.ud, &cfg->ekf, w0);
  else
    rh_ekf_init(&m->f.std, &cfg->ekf, w0);
  rh_rhonn_model_reset(m);
  return 0;
}

/* The known Delta M part's gains at the effectiveness theta (-). */
static void scale_gain(rh_rhonn_model_t *m, real_t theta) {
  m->theta = theta;
  m->kd_now = theta * m->kd0_now;
  m->kd_prev = theta * m->kd0_prev;
}

static real_t *weights(rh_rhonn_model_t *m) {
  return m->ekf_form == RH_EKF_UD ? m->f.ud.W : m->f.std.W;
}

/* The learned Delta M effectiveness's filter when it is on, else NULL (always NULL in a
 * build without it, RH_DM_GAIN 0). */
static rh_yaw_gain_t *gain_filter(rh_rhonn_model_t *m) {
#if RH_DM_GAIN
  return (m->dm_gain_on != 0) ? &m->dm_gain : NULL;
#else
  (void)m;
  return NULL;
#endif
}

int rh_rhonn_model_init_dm_gain(rh_rhonn_model_t *m, const rh_yaw_gain_config_t *cfg) {
  int rc = 0;
  m->dm_gain_on = 0;
#if RH_DM_GAIN
  if (cfg->dm_gain_p0 == 0.0) {
    (void)memset(&m->dm_gain, 0, sizeof m->dm_gain);
  } else {
    int ud = 0;
    if (m->ekf_form == RH_EKF_UD) ud = 1;
    {
      const rh_ekf_config_t *ekf = ud ? &m->f.ud.cfg : &m->f.std.cfg;
      const real_t *w0 = ud ? m->f.ud.w0 : m->f.std.w0;
      rc = rh_yaw_gain_init(&m->dm_gain, cfg, ekf, ud, &w0[2 * RH_NPHI]);
    }
    if (rc == 0) m->dm_gain_on = 1;
  }
#else
  if (cfg->dm_gain_p0 != 0.0) {
    rc = -1; /* this build holds no filter for it */
  }
#endif
  rh_rhonn_model_reset(m);
  return rc;
}

void rh_rhonn_model_sync_dm_gain(rh_rhonn_model_t *m) {
  const rh_yaw_gain_t *g = gain_filter(m);
  scale_gain(m, (g != NULL) ? g->W[RH_YAW_GAIN_THETA] : RH_R(1.0));
}

void rh_rhonn_model_reset(rh_rhonn_model_t *m) {
  int i;
  if (m->ekf_form == RH_EKF_UD)
    rh_ud_ekf_reset(&m->f.ud);
  else
    rh_ekf_reset(&m->f.std);
  {
    rh_yaw_gain_t *g = gain_filter(m);
    if (g != NULL) {
      rh_yaw_gain_reset(g);
    }
  }
  scale_gain(m, RH_R(1.0));
  m->rec_u = RH_R(0.0);
  m->has_record = 0;
  for (i = 0; i < 3; i++) m->rec_chi[i] = (real_t)NAN;
  for (i = 0; i < RH_NPHI; i++) m->rec_phi[i] = RH_R(0.0);
  m->err_ms = m->gate_err_hi * m->gate_err_hi;
  m->learn_steps = 0;
  m->gate_open = 0;
}

const real_t *rh_rhonn_model_weights(const rh_rhonn_model_t *m) {
  return m->ekf_form == RH_EKF_UD ? m->f.ud.W : m->f.std.W;
}

rh_rhonn_view_t rh_rhonn_model_view(const rh_rhonn_model_t *m) {
  rh_rhonn_view_t v;
  int j;
  v.W = rh_rhonn_model_weights(m);
  for (j = 0; j < RH_NXI; j++) {
    v.mu[j] = m->mu[j];
    v.beta[j] = m->beta[j];
  }
  v.increment = m->increment;
  return v;
}

int rh_rhonn_model_observe(rh_rhonn_model_t *m, const real_t x[3], int learn) {
  real_t e[3];
  int ok;
  if (!learn) {
    if (m->ekf_form == RH_EKF_UD)
      rh_ud_ekf_freeze(&m->f.ud);
    else
      rh_ekf_freeze(&m->f.std);
    return 0;
  }
  if (!m->has_record) return 0;
  if (m->ekf_form == RH_EKF_UD)
    ok = rh_ud_ekf_update_error(&m->f.ud, m->rec_phi, x, m->rec_chi, e);
  else
    ok = rh_ekf_update_error(&m->f.std, m->rec_phi, x, m->rec_chi, e);
  /* the joint filter owns the yaw row: its weights replace the EKF's */
  {
    rh_yaw_gain_t *g = gain_filter(m);
    if (ok && (g != NULL) && rh_yaw_gain_update(g, m->rec_phi, m->rec_u, e[2])) {
      real_t *W = weights(m);
      int k;
      for (k = 0; k < RH_NPHI; k++) W[2 * RH_NPHI + k] = g->W[k];
      scale_gain(m, g->W[RH_YAW_GAIN_THETA]);
    }
  }
  if (ok) {
    real_t er = e[2], a = m->gate_a;
    m->err_ms = a * m->err_ms + (RH_R(1.0) - a) * er * er;
    m->learn_steps += 1;
  }
  return ok;
}

real_t rh_rhonn_model_confidence(rh_rhonn_model_t *m) {
  real_t rms, conf;
  if (!m->gate_on || m->gate_open) return RH_R(1.0);
  if (m->learn_steps < m->gate_n) return RH_R(0.0);
  rms = RH_SQRT(m->err_ms);
  conf = (m->gate_err_hi - rms) / (m->gate_err_hi - m->gate_err_lo);
  conf = conf < RH_R(0.0) ? RH_R(0.0) : (conf > RH_R(1.0) ? RH_R(1.0) : conf);
  if (conf >= RH_R(1.0)) m->gate_open = 1; /* latched: see RhonnModel.confidence */
  return conf;
}

/* phi of (x, dw) and out = [x +] known + W phi; returns the finiteness of out. */
static int predict(const rh_rhonn_model_t *m, real_t x0, real_t x1, real_t x2, real_t dw,
                   real_t kt, real_t kdm, real_t phi[RH_NPHI], real_t out[3]) {
  const real_t *W = rh_rhonn_model_weights(m);
  real_t wx[3];
  int r, k;
  rh_rhonn_phi(m->mu[0] * RH_TANH(m->beta[0] * x0), m->mu[1] * RH_TANH(m->beta[1] * x1),
               m->mu[2] * RH_TANH(m->beta[2] * x2), m->mu[3] * RH_TANH(m->beta[3] * dw), phi);
  for (r = 0; r < 3; r++) {
    real_t acc = RH_R(0.0);
    for (k = 0; k < RH_NPHI; k++) acc += W[r * RH_NPHI + k] * phi[k];
    wx[r] = acc;
  }
  if (m->increment) {
    out[0] = x0 + kt + wx[0];
    out[1] = x1 + wx[1];
    out[2] = x2 + kdm + wx[2];
  } else {
    out[0] = kt + wx[0];
    out[1] = wx[1];
    out[2] = kdm + wx[2];
  }
  return RH_FINITE(out[0] + out[1] + out[2]);
}

void rh_rhonn_model_record(rh_rhonn_model_t *m, const real_t x[3], real_t dm,
                           const rh_ctx_t *ctx, real_t out[3]) {
  real_t phi[RH_NPHI];
  real_t kt = m->kt_ts * ctx->total_torque;
  real_t kdm = m->kd_now * dm + m->kd_prev * ctx->delta_m_prev;
  int k;
  if (predict(m, x[0], x[1], x[2], ctx->delta_w, kt, kdm, phi, out)) {
    for (k = 0; k < RH_NPHI; k++) m->rec_phi[k] = phi[k];
    for (k = 0; k < 3; k++) m->rec_chi[k] = out[k];
    if (m->dm_gain_on) m->rec_u = m->kd0_now * dm + m->kd0_prev * ctx->delta_m_prev;
    m->has_record = 1;
  } else {
    m->has_record = 0;
  }
}

void rh_rhonn_model_forget(rh_rhonn_model_t *m) { m->has_record = 0; }

void rh_rhonn_model_b_prev(const rh_rhonn_model_t *m, real_t b_prev[3]) {
  b_prev[0] = RH_R(0.0);
  b_prev[1] = RH_R(0.0);
  b_prev[2] = m->kd_prev;
}

void rh_rhonn_model_rollout(const rh_rhonn_model_t *m, const real_t x0[3], const real_t *ubar,
                            int n, const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B) {
  const real_t *W = rh_rhonn_model_weights(m);
  const real_t *mu = m->mu, *be = m->beta;
  real_t kt = m->kt_ts * ctx->total_torque;
  real_t kd = m->kd_now, kp = m->kd_prev, up = ctx->delta_m_prev;
  real_t d = mu[3] * RH_TANH(be[3] * ctx->delta_w);
  real_t x0f = x0[0], x1f = x0[1], x2f = x0[2];
  real_t phi_ext[RH_NPHI + 2];
  real_t dxi[3], wx[3];
  int i, r, j, k;
  xbar[0] = x0f;
  xbar[1] = x1f;
  xbar[2] = x2f;
  phi_ext[0] = RH_R(1.0);
  phi_ext[RH_NPHI + 1] = RH_R(0.0);
  for (i = 0; i < n; i++) {
    real_t ta = RH_TANH(be[0] * x0f), tb = RH_TANH(be[1] * x1f), tc = RH_TANH(be[2] * x2f);
    real_t ui;
    rh_rhonn_phi(mu[0] * ta, mu[1] * tb, mu[2] * tc, d, phi_ext + 1);
    dxi[0] = mu[0] * be[0] * (RH_R(1.0) - ta * ta);
    dxi[1] = mu[1] * be[1] * (RH_R(1.0) - tb * tb);
    dxi[2] = mu[2] * be[2] * (RH_R(1.0) - tc * tc);
    for (r = 0; r < 3; r++) {
      real_t w0 = RH_R(0.0);
      for (k = 0; k < RH_NPHI; k++) w0 += W[r * RH_NPHI + k] * phi_ext[k + 1];
      wx[r] = w0;
      for (j = 0; j < 3; j++) {
        real_t acc = RH_R(0.0);
        for (k = 0; k < RH_NPHI; k++) acc += W[r * RH_NPHI + k] * (phi_ext[DERIV[j][k]] * dxi[j]);
        A[i * 9 + r * 3 + j] = (m->increment && r == j) ? acc + RH_R(1.0) : acc;
      }
    }
    ui = ubar[i];
    if (m->increment) {
      x0f = x0f + kt + wx[0];
      x1f = x1f + wx[1];
      x2f = x2f + kd * ui + kp * up + wx[2];
    } else {
      x0f = kt + wx[0];
      x1f = wx[1];
      x2f = kd * ui + kp * up + wx[2];
    }
    up = ui;
    xbar[(i + 1) * 3 + 0] = x0f;
    xbar[(i + 1) * 3 + 1] = x1f;
    xbar[(i + 1) * 3 + 2] = x2f;
    B[i * 3 + 0] = RH_R(0.0);
    B[i * 3 + 1] = RH_R(0.0);
    B[i * 3 + 2] = kd;
  }
}
