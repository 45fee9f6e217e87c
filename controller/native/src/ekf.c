/* Standard-form guarded EKF of the RHONN weights (see ekf.h; reference
 * controller/core/learning/ekf.py, whose operation order this follows). */
#include "ekf.h"

#include <string.h>

#define L_ RH_EKF_L
#define LL_ (RH_EKF_L * RH_EKF_L)

static void set_p0(real_t *Pi, real_t p0) {
  int a;
  for (a = 0; a < LL_; a++) Pi[a] = RH_R(0.0);
  for (a = 0; a < L_; a++) Pi[a * L_ + a] = p0;
}

void rh_ekf_tuning_init(rh_ekf_tuning_t *t, const rh_ekf_config_t *cfg,
                        const real_t w0[RH_NW], real_t W0[RH_NW]) {
  int i;
  for (i = 0; i < RH_EKF_N; i++) {
    t->R[i] = (real_t)cfg->r[i];
    t->zeta[i] = (real_t)cfg->zeta[i];
  }
  t->q = (real_t)cfg->q;
  t->p_floor = (real_t)cfg->p_floor;
  t->trace_max = (real_t)cfg->trace_max;
  t->p0 = (real_t)cfg->p0;
  t->w_max = (real_t)cfg->w_max;
  for (i = 0; i < RH_NW; i++) W0[i] = w0 ? w0[i] : RH_R(0.0);
}

void rh_ekf_init(rh_ekf_t *f, const rh_ekf_config_t *cfg, const real_t w0[RH_NW]) {
  (void)memset(f, 0, sizeof(*f));
  f->cfg = *cfg;
  rh_ekf_tuning_init(&f->t, cfg, w0, f->w0);
  rh_ekf_reset(f);
}

void rh_ekf_reset(rh_ekf_t *f) {
  int i;
  for (i = 0; i < RH_NW; i++) f->W[i] = f->w0[i];
  for (i = 0; i < RH_EKF_N; i++) set_p0(&f->P[i * LL_], f->t.p0);
  (void)memset(&f->counters, 0, sizeof(f->counters));
  f->since_eig = 0;
}

void rh_ekf_freeze(rh_ekf_t *f) { f->counters.frozen += 1; }

/* |W| <= wm element-wise; returns 1 when something was clipped. */
static int clip_weights(real_t W[RH_NW], real_t wm) {
  int a, clipped = 0;
  for (a = 0; a < RH_NW; a++) {
    if (W[a] > wm) {
      W[a] = wm;
      clipped = 1;
    } else if (W[a] < -wm) {
      W[a] = -wm;
      clipped = 1;
    }
  }
  return clipped;
}

int rh_ekf_update(rh_ekf_t *f, const real_t h[RH_EKF_L], const real_t e[RH_EKF_N]) {
  real_t ph[RH_EKF_N][L_]; /* P_i H, then u = P_i H / sqrt(s_i), u */
  real_t s[RH_EKF_N];      /* innovation variances, u^2 */
  real_t sh = RH_R(0.0), se = RH_R(0.0), ssum = RH_R(0.0), smin = RH_R(0.0);
  int i, a, b;
  /* Finite check by one sum each (a NaN or +-inf makes the sum non-finite). */
  for (a = 0; a < L_; a++) sh += h[a];
  for (i = 0; i < RH_EKF_N; i++) se += e[i];
  if (!(RH_FINITE(sh) && RH_FINITE(se))) {
    f->counters.rejected += 1;
    return 0;
  }
  for (i = 0; i < RH_EKF_N; i++) {
    const real_t *Pi = &f->P[i * LL_];
    real_t acc_s = RH_R(0.0);
    for (a = 0; a < L_; a++) {
      real_t acc = RH_R(0.0);
      for (b = 0; b < L_; b++) acc += Pi[a * L_ + b] * h[b];
      ph[i][a] = acc;
    }
    for (a = 0; a < L_; a++) acc_s += ph[i][a] * h[a];
    s[i] = acc_s + f->t.R[i];
    ssum += s[i];
    smin = (i == 0 || s[i] < smin) ? s[i] : smin;
  }
  if (!(RH_FINITE(ssum) && smin > RH_R(0.0))) {
    f->counters.rejected += 1;
    return 0;
  }
  for (i = 0; i < RH_EKF_N; i++) {
    real_t *Pi = &f->P[i * LL_];
    real_t *Wi = &f->W[i * L_];
    real_t ze = f->t.zeta[i] * e[i];
    real_t rs = RH_SQRT(s[i]);
    for (a = 0; a < L_; a++) Wi[a] += (ph[i][a] / s[i]) * ze;
    for (a = 0; a < L_; a++) ph[i][a] = ph[i][a] / rs;
    for (a = 0; a < L_; a++) {
      real_t ua = ph[i][a];
      for (b = 0; b < L_; b++) Pi[a * L_ + b] -= ua * ph[i][b];
    }
    for (a = 0; a < L_; a++) Pi[a * L_ + a] += f->t.q;
  }
  /* Guards: diagonal floor, trace bound (reset to p0 I), weight bound. */
  for (i = 0; i < RH_EKF_N; i++) {
    real_t *Pi = &f->P[i * LL_];
    real_t tr = RH_R(0.0);
    for (a = 0; a < L_; a++) {
      if (Pi[a * L_ + a] < f->t.p_floor) Pi[a * L_ + a] = f->t.p_floor;
      tr += Pi[a * L_ + a];
    }
    if (tr > f->t.trace_max) {
      set_p0(Pi, f->t.p0);
      f->counters.trace_resets += 1;
    }
  }
  if (clip_weights(f->W, f->t.w_max)) f->counters.weight_clips += 1;
  f->counters.updates += 1;
  if (f->cfg.eig_check_every > 0) {
    f->since_eig += 1;
    if (f->since_eig >= f->cfg.eig_check_every) {
      f->since_eig = 0;
      (void)rh_ekf_enforce_spd(f);
    }
  }
  return 1;
}

int rh_ekf_update_error(rh_ekf_t *f, const real_t h[RH_EKF_L], const real_t x[RH_EKF_N],
                        const real_t chi[RH_EKF_N], real_t e_out[RH_EKF_N]) {
  int i;
  for (i = 0; i < RH_EKF_N; i++) e_out[i] = x[i] - chi[i];
  return rh_ekf_update(f, h, e_out);
}

/* ---------------------------------------------------------------- eigenvalue floor */

#define NM_ RH_EKF_EIG_MAX
#define NNM_ (RH_EKF_EIG_MAX * RH_EKF_EIG_MAX)

/* Cyclic Jacobi on the symmetric n x n A (n <= RH_EKF_EIG_MAX); see rh_ekf_jacobi_eig. */
static int jacobi_eig(const real_t *A_in, real_t *V, real_t *lam, int n) {
  real_t A[NNM_]; /* working copy, driven to diagonal form, u^2 */
  int nn = n * n;
  int p, q, r, sweep;
  for (p = 0; p < nn; p++) A[p] = A_in[p];
  for (p = 0; p < nn; p++) V[p] = RH_R(0.0);
  for (p = 0; p < n; p++) V[p * n + p] = RH_R(1.0);
  for (sweep = 1; sweep <= RH_EKF_JACOBI_SWEEPS; sweep++) {
    real_t off = RH_R(0.0);
    for (p = 0; p < n - 1; p++)
      for (q = p + 1; q < n; q++) off += RH_FABS(A[p * n + q]);
    if (off == RH_R(0.0) || !RH_FINITE(off)) break; /* diagonal (or hopeless: NaN/inf) */
    for (p = 0; p < n - 1; p++) {
      for (q = p + 1; q < n; q++) {
        real_t apq = A[p * n + q];
        real_t g = RH_R(100.0) * RH_FABS(apq);
        real_t theta, t, c, sn, tau;
        if (apq == RH_R(0.0)) continue;
        /* After 3 sweeps an element negligible against both diagonal entries is zeroed
         * (Numerical Recipes' rule): guarantees off == 0 is reached. */
        if (sweep > 3 && RH_FABS(A[p * n + p]) + g == RH_FABS(A[p * n + p]) &&
            RH_FABS(A[q * n + q]) + g == RH_FABS(A[q * n + q])) {
          A[p * n + q] = A[q * n + p] = RH_R(0.0);
          continue;
        }
        /* Rotation annihilating A_pq: t = tan(angle), smaller root (|angle| <= pi/4). */
        theta = (A[q * n + q] - A[p * n + p]) / (RH_R(2.0) * apq);
        t = RH_R(1.0) / (RH_FABS(theta) + RH_SQRT(RH_R(1.0) + theta * theta));
        if (theta < RH_R(0.0)) t = -t;
        c = RH_R(1.0) / RH_SQRT(RH_R(1.0) + t * t);
        sn = t * c;
        tau = sn / (RH_R(1.0) + c);
        A[p * n + p] -= t * apq;
        A[q * n + q] += t * apq;
        A[p * n + q] = A[q * n + p] = RH_R(0.0);
        for (r = 0; r < n; r++) {
          real_t gr, hr;
          if (r == p || r == q) continue;
          gr = A[r * n + p];
          hr = A[r * n + q];
          A[r * n + p] = A[p * n + r] = gr - sn * (hr + gr * tau);
          A[r * n + q] = A[q * n + r] = hr + sn * (gr - hr * tau);
        }
        for (r = 0; r < n; r++) {
          real_t gr = V[r * n + p], hr = V[r * n + q];
          V[r * n + p] = gr - sn * (hr + gr * tau);
          V[r * n + q] = hr + sn * (gr - hr * tau);
        }
      }
    }
  }
  for (p = 0; p < n; p++) lam[p] = A[p * n + p];
  return sweep;
}

int rh_ekf_jacobi_eig(const real_t A_in[LL_], real_t V[LL_], real_t lam[L_]) {
  return jacobi_eig(A_in, V, lam, L_);
}

/* 1 when every eigenvalue of the symmetric n x n Pi is above floor by more than rounding can
 * blur: a Cholesky factorisation of Pi - (floor + margin) I succeeds with finite, positive
 * pivots. margin = 32 n eps max|diag| covers the factorisation's rounding, so a P_i this test
 * passes has no eigenvalue the floor would change; the others go to the Jacobi path. */
static int clearly_above_floor(const real_t *Pi, int n, real_t floor) {
  real_t C[NNM_];
  real_t dmax = RH_R(0.0), shift;
  int nn = n * n;
  int a, b, k;
  for (a = 0; a < n; a++) {
    real_t d = RH_FABS(Pi[a * n + a]);
    dmax = d > dmax ? d : dmax;
  }
  shift = floor + RH_R(32.0) * (real_t)n * RH_EPS * dmax;
  for (a = 0; a < nn; a++) C[a] = Pi[a];
  for (a = 0; a < n; a++) C[a * n + a] -= shift;
  for (a = 0; a < n; a++) {
    real_t d = C[a * n + a];
    for (k = 0; k < a; k++) d -= C[k * n + a] * C[k * n + a];
    if (!(d > RH_R(0.0)) || !RH_FINITE(d)) return 0;
    d = RH_SQRT(d);
    C[a * n + a] = d;
    for (b = a + 1; b < n; b++) {
      real_t v = C[a * n + b];
      for (k = 0; k < a; k++) v -= C[k * n + a] * C[k * n + b];
      C[a * n + b] = v / d;
    }
  }
  return 1;
}

int rh_ekf_floor_spd(real_t *Pi, int n, real_t p_floor, real_t p0) {
  real_t V[NNM_]; /* eigenvectors (columns), - */
  real_t lam[NM_]; /* eigenvalues, u^2 */
  int nn = n * n;
  int a, b, k;
  int finite = 1;
  int repaired = 0;
  if (n >= 1 && n <= NM_) {
    for (a = 0; a < nn; a++) finite = finite && RH_FINITE(Pi[a]);
    if (!(finite && clearly_above_floor(Pi, n, p_floor))) { /* else unchanged, cheaply */
      if (finite) {
        (void)jacobi_eig(Pi, V, lam, n);
        for (a = 0; a < n; a++) finite = finite && RH_FINITE(lam[a]);
      }
      if (!finite) {
        for (a = 0; a < nn; a++) Pi[a] = RH_R(0.0);
        for (a = 0; a < n; a++) Pi[a * n + a] = p0;
        repaired = 1;
      } else {
        real_t lmin = lam[0];
        for (a = 1; a < n; a++) lmin = lam[a] < lmin ? lam[a] : lmin;
        if (lmin < p_floor) repaired = 1; /* else nothing below the floor: unchanged */
      }
      if (finite && repaired) {
        for (a = 0; a < n; a++) lam[a] = lam[a] < p_floor ? p_floor : lam[a];
        /* P_i = V diag(lam) V', computed on the upper triangle and mirrored (symmetric). */
        for (a = 0; a < n; a++) {
          for (b = a; b < n; b++) {
            real_t acc = RH_R(0.0);
            for (k = 0; k < n; k++) acc += V[a * n + k] * lam[k] * V[b * n + k];
            Pi[a * n + b] = acc;
            Pi[b * n + a] = acc;
          }
        }
      }
    }
  }
  return repaired;
}

int rh_ekf_enforce_spd(rh_ekf_t *f) {
  int i, repaired = 0;
  for (i = 0; i < RH_EKF_N; i++)
    repaired += rh_ekf_floor_spd(&f->P[i * LL_], L_, f->t.p_floor, f->t.p0);
  f->counters.eig_repairs += repaired;
  return repaired;
}

void rh_ekf_sizes(int out[3]) {
  out[0] = (int)sizeof(rh_ekf_t);
  out[1] = (int)sizeof(rh_ekf_config_t);
  out[2] = (int)sizeof(rh_ekf_counters_t);
}
