/* UD-form guarded EKF of the RHONN weights (see ud_ekf.h; reference
 * controller/core/learning/ud_ekf.py, whose operation order this follows). */
#include "ud_ekf.h"

#include <string.h>

#define L_ RH_EKF_L
#define LL_ (RH_EKF_L * RH_EKF_L)
#define NU_ RH_UD_NU

/* U_i(a, j) of the packed factor Ui for a <= j (the unit diagonal included). */
static double u_at(const real_t *Ui, int a, int j) {
  return (a == j) ? 1.0 : (double)Ui[RH_UD_AT(a, j)];
}

static void set_identity(rh_ud_ekf_t *f, int i) {
  real_t *Ui = &f->U[i * NU_];
  int a;
  for (a = 0; a < NU_; a++) {
    Ui[a] = RH_R(0.0);
  }
  for (a = 0; a < L_; a++) {
    f->D[i * L_ + a] = f->t.p0;
  }
}

void rh_ud_ekf_init(rh_ud_ekf_t *f, const rh_ekf_config_t *cfg, const real_t w0[RH_NW]) {
  (void)memset(f, 0, sizeof(*f));
  f->cfg = *cfg;
  rh_ekf_tuning_init(&f->t, cfg, w0, f->w0);
  rh_ud_ekf_reset(f);
}

void rh_ud_ekf_reset(rh_ud_ekf_t *f) {
  int i;
  for (i = 0; i < RH_NW; i++) f->W[i] = f->w0[i];
  for (i = 0; i < RH_EKF_N; i++) set_identity(f, i);
  (void)memset(&f->counters, 0, sizeof(f->counters));
}

void rh_ud_ekf_freeze(rh_ud_ekf_t *f) { f->counters.frozen += 1; }

void rh_ud_add_scaled_identity(real_t *U, real_t *D, int n, int packed, real_t q, real_t *fv) {
  int kk;
  int j;
  int a;
  int step = (packed != 0) ? 1 : n; /* from U(a, j) to U(a + 1, j) */
  /* n rank-one updates P + q e_kk e_kk' (Agee-Turner); for the unit vector e_kk only
   * columns <= kk change. */
  for (kk = 0; kk < n; kk++) {
    real_t c = q;
    for (a = 0; a < n; a++) fv[a] = RH_R(0.0);
    fv[kk] = RH_R(1.0);
    for (j = kk; j >= 0; j--) {
      real_t p = fv[j];
      real_t dj = D[j];
      real_t dn = dj + c * p * p;
      real_t bet = c * p / dn;
      real_t *col = (packed != 0) ? &U[RH_UD_AT(0, j)] : &U[j]; /* U(0, j) */
      c = c * dj / dn;
      D[j] = dn;
      for (a = 0; a < j; a++) {
        fv[a] = fv[a] - p * col[a * step];
        col[a * step] = col[a * step] + bet * fv[a];
      }
    }
  }
}

int rh_ud_ekf_update(rh_ud_ekf_t *f, const real_t h[RH_EKF_L], const real_t e[RH_EKF_N]) {
  real_t k[L_];  /* unnormalised gain, u^2 */
  real_t fv[L_]; /* U' h (measurement), then the rank-one vector (time update), - */
  real_t sh = RH_R(0.0), se = RH_R(0.0);
  int i, j, a, clipped;
  for (a = 0; a < L_; a++) sh += h[a];
  for (i = 0; i < RH_EKF_N; i++) se += e[i];
  if (!(RH_FINITE(sh) && RH_FINITE(se))) {
    f->counters.rejected += 1;
    return 0;
  }
  /* Innovation variances first: reject before touching any state. */
  for (i = 0; i < RH_EKF_N; i++) {
    const real_t *Ui = &f->U[i * NU_];
    real_t s = f->t.R[i];
    for (j = 0; j < L_; j++) {
      const real_t *col = &Ui[RH_UD_AT(0, j)];
      real_t fj = RH_R(0.0);
      for (a = 0; a < j; a++) {
        fj += col[a] * h[a];
      }
      fj += h[j]; /* the unit diagonal, last as in the full sum */
      s += f->D[i * L_ + j] * fj * fj;
    }
    if (!(RH_FINITE(s) && s > RH_R(0.0))) {
      f->counters.rejected += 1;
      return 0;
    }
  }
  for (i = 0; i < RH_EKF_N; i++) {
    real_t *Ui = &f->U[i * NU_];
    real_t *Di = &f->D[i * L_];
    real_t *Wi = &f->W[i * L_];
    real_t alpha, ze;
    /* Bierman: f = U'h, v = D f, sequential scalar update of U, D and the gain k. */
    for (j = 0; j < L_; j++) {
      const real_t *col = &Ui[RH_UD_AT(0, j)];
      real_t fj = RH_R(0.0);
      for (a = 0; a < j; a++) {
        fj += col[a] * h[a];
      }
      fv[j] = fj + h[j];
    }
    alpha = f->t.R[i];
    for (j = 0; j < L_; j++) {
      real_t vj = Di[j] * fv[j];
      real_t beta = alpha;
      real_t lam;
      real_t *col = &Ui[RH_UD_AT(0, j)];
      alpha = alpha + fv[j] * vj;
      lam = -fv[j] / beta;
      Di[j] = Di[j] * (beta / alpha);
      for (a = 0; a < j; a++) {
        real_t tmp = col[a];
        col[a] = tmp + lam * k[a];
        k[a] = k[a] + vj * tmp;
      }
      k[j] = vj;
    }
    ze = f->t.zeta[i] * e[i];
    for (a = 0; a < L_; a++) Wi[a] += (k[a] / alpha) * ze;
    rh_ud_add_scaled_identity(Ui, Di, L_, 1, f->t.q, fv); /* time update P <- P + q I */
  }
  /* Guards: D floor, trace bound (U = I, D = p0), weight bound. */
  for (i = 0; i < RH_EKF_N; i++) {
    const real_t *Ui = &f->U[i * NU_];
    real_t *Di = &f->D[i * L_];
    real_t tr = RH_R(0.0);
    for (j = 0; j < L_; j++) {
      const real_t *uj = &Ui[RH_UD_AT(0, j)];
      real_t col = RH_R(0.0);
      if (Di[j] < f->t.p_floor) Di[j] = f->t.p_floor;
      for (a = 0; a < j; a++) {
        col += uj[a] * uj[a];
      }
      col += RH_R(1.0); /* the unit diagonal, last as in the full sum */
      tr += Di[j] * col;
    }
    if (tr > f->t.trace_max) {
      set_identity(f, i);
      f->counters.trace_resets += 1;
    }
  }
  clipped = 0;
  for (a = 0; a < RH_NW; a++) {
    if (f->W[a] > f->t.w_max) {
      f->W[a] = f->t.w_max;
      clipped = 1;
    } else if (f->W[a] < -f->t.w_max) {
      f->W[a] = -f->t.w_max;
      clipped = 1;
    }
  }
  if (clipped) f->counters.weight_clips += 1;
  f->counters.updates += 1;
  return 1;
}

int rh_ud_ekf_update_error(rh_ud_ekf_t *f, const real_t h[RH_EKF_L],
                           const real_t x[RH_EKF_N], const real_t chi[RH_EKF_N],
                           real_t e_out[RH_EKF_N]) {
  int i;
  for (i = 0; i < RH_EKF_N; i++) e_out[i] = x[i] - chi[i];
  return rh_ud_ekf_update(f, h, e_out);
}

void rh_ud_ekf_covariance(const rh_ud_ekf_t *f, double P[RH_EKF_NP]) {
  int i, a, b, j;
  for (i = 0; i < RH_EKF_N; i++) {
    const real_t *Ui = &f->U[i * NU_];
    const real_t *Di = &f->D[i * L_];
    for (a = 0; a < L_; a++) {
      for (b = a; b < L_; b++) {
        double acc = 0.0;
        /* U upper triangular: only j >= max(a, b) = b contributes. */
        for (j = b; j < L_; j++) acc += u_at(Ui, a, j) * (double)Di[j] * u_at(Ui, b, j);
        P[i * LL_ + a * L_ + b] = acc;
        P[i * LL_ + b * L_ + a] = acc;
      }
    }
  }
}

int rh_ud_ekf_set_covariance(rh_ud_ekf_t *f, const double P[RH_EKF_NP]) {
  double U[LL_]; /* factor of one neuron in double, - */
  double D[L_];  /* u^2 */
  int i, j, a, m, bad = 0;
  for (i = 0; i < RH_EKF_N; i++) {
    const double *Pi = &P[i * LL_];
    for (a = 0; a < LL_; a++) U[a] = 0.0;
    for (a = 0; a < L_; a++) U[a * L_ + a] = 1.0;
    /* Reverse-order Cholesky-type factorisation (Bierman's "UD factor"). */
    for (j = L_ - 1; j >= 0; j--) {
      double acc = 0.0;
      for (m = j + 1; m < L_; m++) acc += U[j * L_ + m] * U[j * L_ + m] * D[m];
      D[j] = Pi[j * L_ + j] - acc;
      if (!(isfinite(D[j]) && D[j] > 0.0)) bad += 1;
      for (a = 0; a < j; a++) {
        double acc2 = 0.0;
        for (m = j + 1; m < L_; m++) acc2 += U[a * L_ + m] * U[j * L_ + m] * D[m];
        U[a * L_ + j] = (Pi[a * L_ + j] - acc2) / D[j];
      }
    }
    for (j = 1; j < L_; j++) {
      for (a = 0; a < j; a++) {
        f->U[i * NU_ + RH_UD_AT(a, j)] = (real_t)U[a * L_ + j];
      }
    }
    for (a = 0; a < L_; a++) f->D[i * L_ + a] = (real_t)D[a];
  }
  return bad;
}

int rh_ud_ekf_size(void) { return (int)sizeof(rh_ud_ekf_t); }
