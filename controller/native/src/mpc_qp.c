/* Condensed linearised MPC on OSQP's generated solver (see mpc_qp.h). */
#include "mpc_qp.h"

#include <math.h>
#include <string.h>

#include "osqp.h"

#define QP_MAGNITUDE_LIMIT 1e12 /* |P|, |q| entries beyond this are meaningless */
#define QP_INF ((OSQPFloat)1e30)  /* OSQP's infinity (the reference's OSQP_INF) */
#ifdef OSQP_USE_FLOAT
#define QP_SQRT(v) sqrtf(v)   /* the FPU's single-precision root in OSQP's float build */
#else
#define QP_SQRT(v) sqrt(v)
#endif
#define SHAPE(qp) ((qp)->env ? 2 : (qp)->rate) /* generated shape: box, + rate, + envelope */

static void apply_settings(rh_qp_t *qp) {
  OSQPSolver *s = rh_qpws_solver(&qp->ws, qp->N, SHAPE(qp));
  const rh_qp_config_t *c = &qp->cfg;
  s->settings->max_iter = c->max_iter;
  s->settings->eps_abs = c->eps_abs;
  s->settings->eps_rel = c->eps_rel;
  s->settings->eps_prim_inf = c->eps_prim_inf;
  s->settings->eps_dual_inf = c->eps_dual_inf;
  s->settings->alpha = c->alpha;
  s->settings->check_termination = c->check_termination;
  s->settings->warm_starting = c->warm_starting;
  s->settings->adaptive_rho_interval = c->adaptive_rho_interval;
  s->settings->scaled_termination = c->scaled_termination;
  s->settings->adaptive_rho_tolerance = c->adaptive_rho_tolerance;
  s->settings->adaptive_rho_fraction = c->adaptive_rho_fraction;
  s->settings->scaling = c->scaling; /* >= 1 (rh_qp_init): the template has the vectors */
}

/* (D2'D2)[a][b] of the N x N second difference D2 (rows i: 1 at i, -2 at i-1, 1 at i-2). */
static double d2_entry(int i, int a) {
  double v = 0.0;
  if (i == a) {
    v = 1.0;
  } else if ((i - 1) == a) {
    v = -2.0;
  } else if ((i - 2) == a) {
    v = 1.0;
  } else {
    v = 0.0;
  }
  return v;
}

static double d2td2(int n, int a, int b) {
  double acc = 0.0;
  int i;
  for (i = 0; i < n; i++) {
    acc += d2_entry(i, a) * d2_entry(i, b);
  }
  return acc;
}

int rh_qp_init(rh_qp_t *qp, const rh_qp_config_t *cfg, double ts_s) {
  int i;
  (void)memset(qp, 0, sizeof *qp);
  if (cfg->horizon < 1 || cfg->horizon > RH_N_MAX || cfg->sqp_iterations < 1 ||
      cfg->sqp_iterations > 10 || !(cfg->u_scale > 0.0) || cfg->scaling < 1)
    return -1;
  qp->cfg = *cfg;
  qp->N = cfg->horizon;
  qp->env = cfg->envelope != 0;
  qp->rate = cfg->rate_limit_nm_per_s > 0.0 || qp->env;
  qp->m = qp->env ? 6 * qp->N + 2 : (qp->rate ? 2 * qp->N : qp->N);
  qp->nv = qp->env ? qp->N + 2 : qp->N;
  qp->nnz_a = qp->N + 2 * qp->N - 1 + 4 * qp->N * qp->N + 4 * qp->N + 2;
  {
    /* 2 lambda I + 2 lambda_D D'D, D = I - shift (the reference's order: double, then real) */
    int a, b, n = qp->N;
    for (a = 0; a < n; a++)
      for (b = 0; b < n; b++) {
        double dtd = a == b ? (a + 1 < n ? 2.0 : 1.0) : ((a - b == 1 || b - a == 1) ? -1.0 : 0.0);
        double r = ((2.0 * cfg->input_reg) * ((a == b) ? 1.0 : 0.0)) +
                   ((2.0 * cfg->delta_rate_weight) * dtd);
        if (cfg->delta_accel_weight > 0.0) {
          r += (2.0 * cfg->delta_accel_weight) * d2td2(n, a, b);
        }
        qp->reg[a * n + b] = (real_t)r;
      }
  }
  qp->u_scale = (real_t)cfg->u_scale;
  qp->v_min = (real_t)cfg->v_min;
  qp->fallback_decay = (real_t)cfg->fallback_decay;
  qp->rate_step = (OSQPFloat)(cfg->rate_limit_nm_per_s * ts_s / cfg->u_scale);
  for (i = 0; i < qp->N; i++) {
    qp->wdiag[2 * i] = (real_t)cfg->q_yaw[i];
    qp->wdiag[2 * i + 1] = (real_t)cfg->r_beta[i];
  }
  if (qp->env) { /* the slacks' prices, constant: after the upper triangle / after q */
    int nt = qp->N * (qp->N + 1) / 2;
    qp->px64[nt] = qp->px64[nt + 1] = (OSQPFloat)(2.0 * cfg->env_slack_quad + 1e-6);
    qp->q64[qp->N] = (OSQPFloat)cfg->env_slack_linear;
    qp->q64[qp->N + 1] = (OSQPFloat)cfg->env_slack_linear;
  }
  if (rh_qpws_init(&qp->ws, qp->N, SHAPE(qp)) != 0) return -2;
  rh_qp_reset(qp);
  return 0;
}

void rh_qp_reset(rh_qp_t *qp) {
  int i;
  for (i = 0; i < RH_N_MAX; i++) {
    qp->sol[i] = RH_R(0.0);
    qp->ubar[i] = RH_R(0.0);
  }
  qp->last_iterations = 0;
  qp->last_status = RH_QP_NOT_RUN;
  qp->has_y_last = 0;
  qp->slack[0] = (OSQPFloat)0.0; qp->slack[1] = (OSQPFloat)0.0;
  qp->zprev = (OSQPFloat)0.0;
  qp->zprev2 = (OSQPFloat)0.0;
  rh_qpws_init(&qp->ws, qp->N, SHAPE(qp));
  apply_settings(qp);
  for (i = 0; i < qp->m; i++) {
    qp->l[i] = (OSQPFloat)-1.0;
    qp->u[i] = (OSQPFloat)1.0;
  }
  qp->bounds_dirty = 1;
  qp->lo_last = (OSQPFloat)NAN; qp->hi_last = (OSQPFloat)NAN;
}

/* Box (N m) and rate-limit rows around the applied Delta M dm_prev (N m). */
static void set_bounds(rh_qp_t *qp, real_t dm_min, real_t dm_max, real_t dm_prev) {
  OSQPFloat us = (OSQPFloat)qp->u_scale;
  OSQPFloat lo = (OSQPFloat)dm_min / us, hi = (OSQPFloat)dm_max / us;
  int i, N = qp->N;
  if (!qp->rate && lo == qp->lo_last && hi == qp->hi_last) return;
  qp->lo_last = lo;
  qp->hi_last = hi;
  qp->bounds_dirty = 1;
  for (i = 0; i < N; i++) {
    qp->lb[i] = (real_t)lo;
    qp->ub[i] = (real_t)hi;
    qp->l[i] = lo;
    qp->u[i] = hi;
  }
  if (qp->rate) {
    OSQPFloat d = qp->rate_step > (OSQPFloat)0.0 ? qp->rate_step : QP_INF;
    OSQPFloat p = RH_FINITE(dm_prev) ? (OSQPFloat)dm_prev / us : (OSQPFloat)0.0;
    if (qp->env) p = p > lo ? (p < hi ? p : hi) : lo; /* a box that shrank below dm_prev */
    qp->l[N] = p - d;
    qp->u[N] = p + d;
    for (i = N + 1; i < 2 * N; i++) {
      qp->l[i] = -d;
      qp->u[i] = d;
    }
  }
}

/* Sensitivities, G, ybar and the QP data P, q; 0 when an entry is non-finite or absurd. */
static int condense_build(rh_qp_t *qp) {
  int n = qp->N, i, a, b, c, r, k;
  const real_t zero = RH_R(0.0), two = RH_R(2.0);
  real_t vmin = qp->v_min, usc = qp->u_scale;
  const real_t lim = (real_t)QP_MAGNITUDE_LIMIT;
  real_t *S = qp->S, *G = qp->G;
  int ok = 1;
#define S_(i, a, c) S[((i) * RH_NX + (a)) * n + (c)]
#define G_(r, c) G[(r) * n + (c)]
  for (a = 0; a < RH_NX; a++) {
    for (c = 0; c < n; c++) S_(0, a, c) = zero;
    S_(0, a, 0) = qp->B[a];
  }
  for (i = 1; i < n; i++) {
    for (a = 0; a < RH_NX; a++) {
      for (c = 0; c < n; c++) {
        real_t acc = zero;
        for (b = 0; b < RH_NX; b++) acc += qp->A[(i * RH_NX + a) * RH_NX + b] * S_(i - 1, b, c);
        S_(i, a, c) = acc;
      }
      S_(i, a, i) += qp->B[i * RH_NX + a];
      if (qp->has_b_prev) S_(i, a, i - 1) += qp->b_prev[a];
    }
  }
  for (i = 0; i < n; i++) {
    real_t xv = qp->xbar[(i + 1) * RH_NX];
    real_t vx = xv > vmin ? xv : vmin; /* also NaN -> v_min (np.fmax) */
    real_t bb = qp->xbar[(i + 1) * RH_NX + 1] / vx;
    real_t t = bb / vx;
    for (c = 0; c < n; c++) {
      real_t g;
      G_(2 * i, c) = S_(i, 2, c) * usc;
      g = S_(i, 1, c) / vx;
      g -= S_(i, 0, c) * t;
      G_(2 * i + 1, c) = g * usc;
    }
    qp->ybar[2 * i] = qp->xbar[(i + 1) * RH_NX + 2];
    qp->ybar[2 * i + 1] = bb;
  }
  for (a = 0; a < n; a++) {
    for (b = 0; b < n; b++) {
      real_t acc = zero;
      for (r = 0; r < 2 * n; r++) acc += G_(r, a) * (G_(r, b) * qp->wdiag[r]);
      qp->Pd[a * n + b] = acc * two + qp->reg[a * n + b];
    }
  }
  /* CSC order of the upper triangle: column by column, rows ascending */
  k = 0;
  for (c = 0; c < n; c++) {
    for (r = 0; r <= c; r++) {
      real_t v = qp->Pd[r * n + c];
      qp->Px[k++] = v;
      if (!(RH_FABS(v) < lim)) ok = 0;
    }
  }
  for (a = 0; a < n; a++) {
    real_t acc = zero;
    for (r = 0; r < 2 * n; r++) {
      real_t gz = zero, rhs;
      for (c = 0; c < n; c++) gz += G_(r, c) * (qp->ubar[c] / usc);
      rhs = gz + qp->yd[r] - qp->ybar[r];
      acc += (G_(r, a) * qp->wdiag[r]) * rhs;
    }
    qp->q[a] = acc * (-two);
    if (a == 0 && qp->cfg.delta_rate_weight > 0.0)   /* -2 lambda_D z_prev */
      qp->q[0] -= (real_t)(2.0 * qp->cfg.delta_rate_weight * (double)qp->zprev);
    if ((a < 2) && (qp->cfg.delta_accel_weight > 0.0)) {
      /* 2 lambda_2 D2'c, c = (z_prev2 - 2 z_prev, z_prev) on rows 0, 1 */
      double zp2 = (double)qp->zprev2;
      double zp = (double)qp->zprev;
      double c0 = zp2 - (2.0 * zp);
      double c1 = zp;
      double w = 2.0 * qp->cfg.delta_accel_weight;
      double dq;
      if (a == 0) {
        double t = 0.0;
        if (n > 1) {
          t = 0.0 - (2.0 * c1);
        }
        dq = w * (c0 + t);
      } else {
        dq = w * c1;
      }
      qp->q[a] += (real_t)dq;
    }
    if (!(RH_FABS(qp->q[a]) < lim)) ok = 0;
  }
#undef S_
#undef G_
  return ok;
}

static int map_status(OSQPInt st) {
  switch (st) {
    case OSQP_SOLVED: return RH_QP_SOLVED;
    case OSQP_SOLVED_INACCURATE: return RH_QP_SOLVED_INACCURATE;
    case OSQP_MAX_ITER_REACHED: return RH_QP_MAX_ITER;
    case OSQP_TIME_LIMIT_REACHED: return RH_QP_MAX_ITER;
    default: return RH_QP_FAILED;
  }
}

/* |v| below the magnitude limit; 0 for NaN and infinities. */
static int usable(double v) { return (v < 0.0 ? -v : v) < QP_MAGNITUDE_LIMIT; }

/* The envelope shape's data (Python: LinearizedMpc._envelope_rows): the envelope rows'
 * Delta M block (aenv, dense) and the envelope rows' bounds.
 * Returns 0, with the envelope rows left inactive, when a row's values or offset are not
 * usable (OSQP would reject l > u or a KKT matrix that is not quasidefinite). Computed in
 * OSQPFloat with the bounds' reciprocals: the FPU's precision in the float build, no
 * per-element double division (~500 instructions each in software on the M4F). */
static int envelope_data(rh_qp_t *qp, const real_t x0[RH_NX], const rh_qp_env_t *env) {
  int n = qp->N;
  int i;
  int c;
  int r0 = 2 * n;
  int valid = 1;
  const rh_qp_config_t *cf = &qp->cfg;
  OSQPFloat *ae = qp->aenv; /* rows: yaw upper, yaw lower, slip upper, slip lower (n each) */
  int on = env != NULL && env->active;
  if (on) { /* every entry of ae is written below; zeroed when the rows are inactive */
    double vx0 = (double)x0[0] > cf->env_v_min_mps ? (double)x0[0] : cf->env_v_min_mps;
    OSQPFloat lead_ay = (OSQPFloat)((cf->env_lead_s * env->ay) / vx0);
    OSQPFloat inv_r = (OSQPFloat)(1.0 / env->r_max);
    OSQPFloat inv_a = (OSQPFloat)(1.0 / env->a_max);
    OSQPFloat lr = (OSQPFloat)cf->env_lr_m;
    OSQPFloat lead = (OSQPFloat)cf->env_lead_s;
    for (i = 0; i < n; i++) {
      real_t xv = qp->xbar[(i + 1) * RH_NX];
      real_t vx = xv > qp->v_min ? xv : qp->v_min; /* the cost's floored Vx (np.fmax) */
      OSQPFloat cc = (lr / (OSQPFloat)vx) + lead;
      OSQPFloat yr = (OSQPFloat)qp->ybar[2 * i];
      OSQPFloat ya = (OSQPFloat)qp->ybar[(2 * i) + 1] - (yr * cc);
      OSQPFloat sr = (OSQPFloat)0.0;
      OSQPFloat sa = (OSQPFloat)0.0;
      OSQPFloat hr;
      OSQPFloat ha;
      ya += lead_ay;
      for (c = 0; c < n; c++) {
        OSQPFloat gr = (OSQPFloat)qp->G[((2 * i) * n) + c];
        OSQPFloat ga = (OSQPFloat)qp->G[(((2 * i) + 1) * n) + c] - (gr * cc);
        OSQPFloat zb = (OSQPFloat)qp->ubar[c] / (OSQPFloat)qp->u_scale;
        sr += gr * zb;
        sa += ga * zb;
        ae[(i * n) + c] = gr * inv_r;
        ae[((n + i) * n) + c] = gr * inv_r;
        ae[(((2 * n) + i) * n) + c] = ga * inv_a;
        ae[(((3 * n) + i) * n) + c] = ga * inv_a;
        if (!usable((double)(gr * inv_r)) || !usable((double)(ga * inv_a))) {
          valid = 0;
        }
      }
      hr = (yr - sr) * inv_r;
      ha = (ya - sa) * inv_a;
      if (!usable((double)hr) || !usable((double)ha)) {
        valid = 0;
      }
      qp->l[r0 + i] = -QP_INF;
      qp->u[r0 + i] = (OSQPFloat)1.0 - hr;
      qp->l[(r0 + n) + i] = (OSQPFloat)-1.0 - hr;
      qp->u[(r0 + n) + i] = QP_INF;
      qp->l[(r0 + (2 * n)) + i] = -QP_INF;
      qp->u[(r0 + (2 * n)) + i] = (OSQPFloat)1.0 - ha;
      qp->l[(r0 + (3 * n)) + i] = (OSQPFloat)-1.0 - ha;
      qp->u[(r0 + (3 * n)) + i] = QP_INF;
    }
    on = valid;
  }
  if (!on) {
    for (i = 0; i < (4 * n * n); i++) {
      ae[i] = (OSQPFloat)0.0;
    }
    for (i = r0; i < (r0 + (4 * n)); i++) {
      qp->l[i] = -QP_INF;
      qp->u[i] = QP_INF;
    }
  }
  qp->l[6 * n] = (OSQPFloat)0.0;
  qp->l[(6 * n) + 1] = (OSQPFloat)0.0;
  qp->u[6 * n] = QP_INF;
  qp->u[(6 * n) + 1] = QP_INF;
  return valid;
}

/* A's values of the envelope shape in CSC order (column by column, rows ascending, as
 * envelope_pattern), from the dense envelope rows aenv: only OSQP needs them. */
static void envelope_csc_values(rh_qp_t *qp) {
  int n = qp->N;
  int i;
  int c;
  int k = 0;
  const OSQPFloat *ae = qp->aenv;
  for (c = 0; c < n; c++) {
    qp->ax[k] = (OSQPFloat)1.0; /* box row c */
    k++;
    qp->ax[k] = (OSQPFloat)1.0; /* rate row n + c */
    k++;
    if ((c + 1) < n) {
      qp->ax[k] = (OSQPFloat)-1.0; /* rate row n + c + 1 */
      k++;
    }
    for (i = 0; i < (4 * n); i++) { /* yaw, then rear slip rows */
      qp->ax[k] = ae[(i * n) + c];
      k++;
    }
  }
  for (i = 0; i < (2 * n); i++) { /* the slacks: -1 on the upper rows, +1 on the lower */
    qp->ax[k] = (i < n) ? (OSQPFloat)-1.0 : (OSQPFloat)1.0; /* s_r: yaw rows */
    k++;
  }
  qp->ax[k] = (OSQPFloat)1.0; /* s_r >= 0 */
  k++;
  for (i = 0; i < (2 * n); i++) {
    qp->ax[k] = (i < n) ? (OSQPFloat)-1.0 : (OSQPFloat)1.0; /* s_a: slip rows */
    k++;
  }
  qp->ax[k] = (OSQPFloat)1.0; /* s_a >= 0 */
}

/* Forget OSQP's iterate after a failed solve: a NaN iterate would otherwise be
 * warm-started into every later solve. */
static void cold_start(rh_qp_t *qp) {
  OSQPFloat xz[RH_NV_MAX], yz[RH_M_MAX];
  int i;
  for (i = 0; i < qp->nv; i++) xz[i] = (OSQPFloat)0.0;
  for (i = 0; i < qp->m; i++) yz[i] = (OSQPFloat)0.0;
  osqp_warm_start(rh_qpws_solver(&qp->ws, qp->N, SHAPE(qp)), xz, yz);
}

static OSQPFloat larger(OSQPFloat a, OSQPFloat b) { return (a > b) ? a : b; }

/* The envelope shape when the box holds every Delta M stage at one value c (l = u on the box
 * rows): x = c and each slack the smallest that satisfies its rows (the cost is increasing in
 * a slack >= 0, so that is the QP's unique solution). The rate rows hold there: the first is
 * anchored to the applied Delta M clipped into the box (set_bounds), i.e. to c, the others
 * see equal stages. The envelope rows' data are finite (envelope_data refused others).
 * 1 when this applies, else 0 (Python: LinearizedMpc._fixed_box_solution). */
static int fixed_box_solution(rh_qp_t *qp, OSQPFloat x[RH_NV_MAX]) {
  int n = qp->N;
  int i;
  int k;
  int side;
  int ok = qp->env;
  for (i = 0; i < n; i++) {
    if (!(qp->l[i] == qp->u[i])) { /* NaN fails too */
      ok = 0;
    }
    x[i] = qp->l[i];
  }
  for (side = 0; (ok != 0) && (side < 2); side++) { /* s_r: yaw rows, s_alpha: slip rows */
    int r0 = (2 + (2 * side)) * n;                      /* the upper rows; the lower follow */
    OSQPFloat need = (OSQPFloat)0.0;
    for (i = 0; i < n; i++) {
      OSQPFloat up = (OSQPFloat)0.0;
      OSQPFloat down = (OSQPFloat)0.0;
      for (k = 0; k < n; k++) {
        up += qp->aenv[((r0 - (2 * n) + i) * n) + k] * x[k];
        down += qp->aenv[((r0 - n + i) * n) + k] * x[k];
      }
      need = larger(need, up - qp->u[r0 + i]);
      need = larger(need, qp->l[r0 + n + i] - down);
    }
    x[n + side] = need;
  }
  return ok;
}

/* The cost's minimiser in x (nv, decision units): Delta M = -P_zz^-1 q_z by Cholesky of P's
 * Delta M block (px64: upper triangle in CSC order), the slacks 0. 1 when it satisfies every
 * row l <= A x <= u (it is then the QP's solution), else 0 (Python:
 * LinearizedMpc._unconstrained_minimiser). */
static int unconstrained_minimiser(rh_qp_t *qp, OSQPFloat x[RH_NV_MAX]) {
  OSQPFloat L[RH_N_MAX * RH_N_MAX];
  OSQPFloat w[RH_N_MAX];
  OSQPFloat az[RH_M_MAX];
  int n = qp->N;
  int i;
  int j;
  int k;
  int ok = 1;
  /* L L' = P_zz, column by column; P(r, c), r <= c, at c (c + 1) / 2 + r */
  for (j = 0; j < n; j++) {
    for (i = j; i < n; i++) {
      OSQPFloat acc = qp->px64[((i * (i + 1)) / 2) + j];
      for (k = 0; k < j; k++) {
        acc -= L[(i * n) + k] * L[(j * n) + k];
      }
      if (i == j) {
        if (!(acc > (OSQPFloat)0.0)) { /* not positive definite (or NaN): OSQP solves */
          ok = 0;
          acc = (OSQPFloat)1.0;          /* keeps the rest of the factor finite */
        }
        L[(j * n) + j] = QP_SQRT(acc);
      } else {
        L[(i * n) + j] = acc / L[(j * n) + j];
      }
    }
  }
  if (ok != 0) {
    for (i = 0; i < n; i++) { /* L w = -q */
      OSQPFloat acc = -qp->q64[i];
      for (k = 0; k < i; k++) {
        acc -= L[(i * n) + k] * w[k];
      }
      w[i] = acc / L[(i * n) + i];
    }
    for (i = n - 1; i >= 0; i--) { /* L' z = w */
      OSQPFloat acc = w[i];
      for (k = i + 1; k < n; k++) {
        acc -= L[(k * n) + i] * x[k];
      }
      x[i] = acc / L[(i * n) + i];
    }
    for (i = n; i < qp->nv; i++) {
      x[i] = (OSQPFloat)0.0;
    }
    for (i = 0; i < n; i++) {
      az[i] = x[i];
    }
    if (qp->rate != 0) {
      az[n] = x[0];
      for (i = 1; i < n; i++) {
        az[n + i] = x[i] - x[i - 1];
      }
    }
    if (qp->env != 0) {
      for (i = 0; i < (4 * n); i++) {
        OSQPFloat acc = (OSQPFloat)0.0;
        for (k = 0; k < n; k++) {
          acc += qp->aenv[(i * n) + k] * x[k];
        }
        az[(2 * n) + i] = acc;
      }
      az[6 * n] = (OSQPFloat)0.0;
      az[(6 * n) + 1] = (OSQPFloat)0.0;
    }
    for (i = 0; i < qp->m; i++) {
      if (!((az[i] >= qp->l[i]) && (az[i] <= qp->u[i]))) { /* NaN fails too */
        ok = 0;
      }
    }
  }
  return ok;
}

/* One OSQP update + solve on px64, q64 (l, u when dirty; A and l, u every round with the
 * envelope); returns the mapped status. */
static int osqp_round(rh_qp_t *qp, int *iters) {
  OSQPSolver *s = rh_qpws_solver(&qp->ws, qp->N, SHAPE(qp));
  int nnz = qp->N * (qp->N + 1) / 2;
  if (qp->env) {
    envelope_csc_values(qp);
    osqp_update_data_vec(s, qp->q64, qp->l, qp->u);
    osqp_update_data_mat(s, qp->px64, OSQP_NULL, nnz + 2, qp->ax, OSQP_NULL, qp->nnz_a);
    qp->bounds_dirty = 0;
  } else {
    if (qp->bounds_dirty) {
      osqp_update_data_vec(s, qp->q64, qp->l, qp->u);
      qp->bounds_dirty = 0;
    } else {
      osqp_update_data_vec(s, qp->q64, OSQP_NULL, OSQP_NULL);
    }
    osqp_update_data_mat(s, qp->px64, OSQP_NULL, nnz, OSQP_NULL, OSQP_NULL, 0);
  }
  osqp_solve(s);
  *iters = (int)s->info->iter;
  return map_status(s->info->status_val);
}

void rh_qp_solve(rh_qp_t *qp, rh_rollout_fn rollout, const void *model, const real_t x0[RH_NX],
                 const rh_ctx_t *ctx, real_t yaw_ref, real_t beta_ref, real_t dm_min,
                 real_t dm_max, real_t dm_prev, const rh_qp_env_t *env, real_t *dm,
                 int *status, int *iterations, int *fallback) {
  OSQPSolver *s = rh_qpws_solver(&qp->ws, qp->N, SHAPE(qp));
  int n = qp->N, i, round, iters = 0, st = RH_QP_FAILED, ok = 0, nnz = n * (n + 1) / 2;
  real_t usc = qp->u_scale;
  set_bounds(qp, dm_min, dm_max, dm_prev);
  qp->zprev2 = qp->zprev;
  qp->zprev = RH_FINITE(dm_prev) ? (OSQPFloat)((double)dm_prev / (double)usc) : (OSQPFloat)0.0;
  /* nominal input: previous solution shifted one stage (last repeated), clipped */
  for (i = 0; i < n - 1; i++) qp->ubar[i] = qp->sol[i + 1];
  qp->ubar[n - 1] = qp->sol[n - 1];
  for (i = 0; i < n; i++) {
    real_t v = qp->ubar[i] > dm_min ? qp->ubar[i] : dm_min;
    qp->ubar[i] = v < dm_max ? v : dm_max;
    qp->yd[2 * i] = yaw_ref;
    qp->yd[2 * i + 1] = beta_ref;
  }
  for (round = 0; round < qp->cfg.sqp_iterations; round++) {
    int it = 0;
    OSQPFloat sum = (OSQPFloat)0.0, xu[RH_NV_MAX];
    const OSQPFloat *x;
    rollout(model, x0, qp->ubar, n, ctx, qp->xbar, qp->A, qp->B);
    if (!condense_build(qp)) {
      st = RH_QP_FAILED;
      ok = 0;
      break;
    }
    for (i = 0; i < nnz; i++) qp->px64[i] = (OSQPFloat)qp->Px[i];
    for (i = 0; i < n; i++) qp->q64[i] = (OSQPFloat)qp->q[i];
    if (qp->env && !envelope_data(qp, x0, env)) { /* absurd envelope data: OSQP untouched */
      st = RH_QP_FAILED;
      ok = 0;
      break;
    }
    if (qp->cfg.unconstrained_first &&
        (fixed_box_solution(qp, xu) || unconstrained_minimiser(qp, xu))) {
      st = RH_QP_SOLVED;
      ok = 1;
      qp->unconstrained_solves += 1;
      for (i = 0; i < qp->m; i++) qp->y_last[i] = (OSQPFloat)0.0;
      qp->has_y_last = 1;
      osqp_warm_start(s, xu, qp->y_last);   /* OSQP starts from it when a row next binds */
      x = xu;
    } else {
      st = osqp_round(qp, &it);
      iters += it;
      if (st != RH_QP_FAILED) {
        for (i = 0; i < n; i++) sum += s->solution->x[i];
        ok = RH_FINITE(sum);
      }
      if (!ok) {
        st = RH_QP_FAILED;
        cold_start(qp);
        break;
      }
      for (i = 0; i < qp->m; i++) qp->y_last[i] = s->solution->y[i];
      qp->has_y_last = 1;
      x = s->solution->x;
    }
    if (qp->env) {
      qp->slack[0] = x[n];
      qp->slack[1] = x[n + 1];
    }
    for (i = 0; i < n; i++) {
      real_t v = (real_t)x[i];
      v = v > qp->lb[i] ? v : qp->lb[i];
      qp->z[i] = v < qp->ub[i] ? v : qp->ub[i];
      qp->ubar[i] = qp->z[i] * usc;
    }
  }
  qp->last_iterations = iters;
  if (iters > qp->worst_iterations) qp->worst_iterations = iters;
  if (st == RH_QP_MAX_ITER) qp->max_iter_hits += 1;
  *iterations = iters;
  if (ok) {
    for (i = 0; i < n; i++) qp->sol[i] = qp->ubar[i];
    qp->last_status = st;
    *dm = qp->ubar[0];
    *status = st;
    *fallback = 0;
    return;
  }
  /* Fallback: decay the previous command, keep it inside the box. */
  qp->fallbacks += 1;
  {
    real_t d = qp->fallback_decay * (RH_FINITE(dm_prev) ? dm_prev : RH_R(0.0));
    d = d > dm_min ? d : dm_min;
    d = d < dm_max ? d : dm_max;
    for (i = 0; i < n; i++) qp->sol[i] = d;
    qp->last_status = RH_QP_FALLBACK;
    *dm = d;
    *status = RH_QP_FALLBACK;
    *fallback = 1;
  }
}

void rh_qp_warm_start(rh_qp_t *qp, const OSQPFloat *x, const OSQPFloat *y) {
  OSQPSolver *s = rh_qpws_solver(&qp->ws, qp->N, SHAPE(qp));
  OSQPFloat xb[RH_NV_MAX], yb[RH_M_MAX];
  int i;
  if (x) {
    for (i = 0; i < qp->N; i++) xb[i] = x[i];
    if (qp->env) {   /* the reference warm-starts the slacks from the last solution */
      xb[qp->N] = qp->slack[0];
      xb[qp->N + 1] = qp->slack[1];
    }
  }
  if (y) {
    for (i = 0; i < qp->m; i++) {
      yb[i] = y[i];
      qp->y_last[i] = y[i];
    }
    qp->has_y_last = 1;
  }
  osqp_warm_start(s, x ? xb : OSQP_NULL, y ? yb : OSQP_NULL);
}

void rh_qp_copy(rh_qp_t *dst, const rh_qp_t *src) {
  /* everything but the workspace is plain data; the workspace is relocated */
  (void)memcpy(dst, src, sizeof *dst);
  rh_qpws_copy(&dst->ws, &src->ws, src->N, SHAPE(src));
}
