/* Guarded Heun sub-stepping with forward-mode sensitivities (see substep.h).
 * Operation order follows controller/core/model/_substep.py so that the float64 build
 * reproduces the reference to rounding. */
#include "substep.h"

/* Tolerance of the sub-step count's ceil(), on the ratio (-): the reference subtracts 1e-9.
 * In float32 ts arrives rounded (0.05f = 0.05 * (1 + 1.5e-8)), which would turn
 * ceil(0.05f/0.05) into 2: allow 4 float ulps relative on top. */
#ifdef RH_FLOAT32
#define RH_SUBSTEP_RTOL 2.4e-7
#else
#define RH_SUBSTEP_RTOL 0.0
#endif

double rh_substep_stiffness_rate(double cf_n_per_rad, double cr_n_per_rad, double mass_kg,
                                 double yaw_inertia_kgm2, double lf_m, double lr_m) {
  double cf = fabs(cf_n_per_rad), cr = fabs(cr_n_per_rad);
  double a = (cf + cr) / mass_kg;                                     /* 1/s * m/s */
  double b = (cf * lf_m * lf_m + cr * lr_m * lr_m) / yaw_inertia_kgm2; /* m/s^2 */
  /* 1.25: margin for the coupling terms (Table 1 car: bound 104.5, true max 107.7) */
  return 1.25 * (a > b ? a : b);
}

/* ceil(ratio - tol) as a count in [0, RH_SUBSTEP_MAX + 1] (no int overflow). */
static int ceil_count(double ratio) {
  double c = ceil(ratio - (1e-9 + RH_SUBSTEP_RTOL * ratio));
  if (c > (double)RH_SUBSTEP_MAX) return RH_SUBSTEP_MAX + 1;
  if (c < 0.0) return 0;
  return (int)c;
}

int rh_substep_count(const real_t x[3], real_t delta_m, const rh_ctx_t *ctx, double h_max_s,
                     double stiff_rate) {
  double ts = (double)ctx->ts; /* s */
  double vabs, lam;
  int n1, n2, n;
  if (!(RH_FINITE(x[0]) && RH_FINITE(x[1]) && RH_FINITE(x[2]) && RH_FINITE(delta_m) &&
        RH_FINITE(ctx->delta_w) && RH_FINITE(ctx->total_torque) && RH_FINITE(ctx->ts)))
    return 0;
  if (!(ts > 0.0 && ts <= RH_SUBSTEP_MAX_TS_S)) return 0;
  vabs = fabs((double)x[0]);
  lam = stiff_rate / (vabs > RH_SUBSTEP_V_LOW_MPS ? vabs : RH_SUBSTEP_V_LOW_MPS); /* 1/s */
  n1 = ceil_count(ts / h_max_s);
  n2 = ceil_count(ts * lam / RH_SUBSTEP_H_LAMBDA_MAX);
  n = n1 > n2 ? n1 : n2;
  if (n < 1) n = 1;
  if (n > RH_SUBSTEP_MAX) n = RH_SUBSTEP_MAX;
  return n;
}

void rh_substep_fail(real_t xn[3], real_t A[9], real_t B[3]) {
  int k;
  if (xn != 0)
    for (k = 0; k < 3; k++) xn[k] = (real_t)NAN;
  for (k = 0; k < 9; k++) A[k] = (real_t)NAN;
  for (k = 0; k < 3; k++) B[k] = (real_t)NAN;
}

void rh_substep_initial_state(real_t vx, real_t vy, real_t yaw_rate, real_t x[3]) {
  x[0] = vx;
  x[1] = vy;
  x[2] = yaw_rate;
}

void rh_substep_predict(rh_substep_rhs_fn rhs, const void *call, int n, real_t ts,
                        const real_t x[3], real_t xn[3]) {
  real_t h = ts / (real_t)n; /* s */
  real_t hh = RH_R(0.5) * h;
  real_t vx = x[0], vy = x[1], r = x[2];
  real_t a[3], b[3];
  int i;
  for (i = 0; i < n && i < RH_SUBSTEP_MAX; i++) {
    rhs(call, vx, vy, r, a);
    rhs(call, vx + h * a[0], vy + h * a[1], r + h * a[2], b);
    vx += hh * (a[0] + b[0]);
    vy += hh * (a[1] + b[1]);
    r += hh * (a[2] + b[2]);
  }
  if (!(RH_FINITE(vx) && RH_FINITE(vy) && RH_FINITE(r))) {
    xn[0] = (real_t)NAN; xn[1] = (real_t)NAN; xn[2] = (real_t)NAN;
    return;
  }
  xn[0] = vx;
  xn[1] = vy;
  xn[2] = r;
}

/* out = J S for J = g[3..11] and S, both 3x3 row-major (reference _jm). */
static void jm(const real_t g[15], const real_t S[9], real_t out[9]) {
  int i, j;
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++)
      out[3 * i + j] = g[3 + 3 * i] * S[j] + g[4 + 3 * i] * S[3 + j] + g[5 + 3 * i] * S[6 + j];
}

/* out = J v for J = g[3..11] (reference _jv). */
static void jv(const real_t g[15], const real_t v[3], real_t out[3]) {
  int i;
  for (i = 0; i < 3; i++) out[i] = g[3 + 3 * i] * v[0] + g[4 + 3 * i] * v[1] + g[5 + 3 * i] * v[2];
}

void rh_substep_propagate(rh_substep_rhs_jac_fn rhs_jac, const void *call, int n, real_t ts,
                          const real_t x[3], real_t xn[3], real_t A[9], real_t B[3]) {
  real_t h = ts / (real_t)n; /* s */
  real_t hh = RH_R(0.5) * h;
  real_t z0 = x[0], z1 = x[1], z2 = x[2];
  real_t S[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}; /* dz/dx0 */
  real_t sb[3] = {0, 0, 0};                  /* dz/dDeltaM, per N m */
  real_t ga[15], gb[15], JS[9], JS1[9], S1[9], ua[3], u[3], w[3], vb[3];
  real_t tot, ssum;
  int i, k;
  for (i = 0; i < n && i < RH_SUBSTEP_MAX; i++) {
    rhs_jac(call, z0, z1, z2, ga);
    jm(ga, S, JS);
    jv(ga, sb, ua);
    for (k = 0; k < 3; k++) u[k] = ua[k] + ga[12 + k];
    for (k = 0; k < 9; k++) S1[k] = S[k] + h * JS[k];
    rhs_jac(call, z0 + h * ga[0], z1 + h * ga[1], z2 + h * ga[2], gb);
    jm(gb, S1, JS1);
    for (k = 0; k < 3; k++) w[k] = sb[k] + h * u[k];
    jv(gb, w, vb);
    for (k = 0; k < 9; k++) S[k] = S[k] + hh * (JS[k] + JS1[k]);
    for (k = 0; k < 3; k++) sb[k] = sb[k] + hh * (u[k] + vb[k] + gb[12 + k]);
    z0 += hh * (ga[0] + gb[0]);
    z1 += hh * (ga[1] + gb[1]);
    z2 += hh * (ga[2] + gb[2]);
  }
  /* same finiteness test as the reference: z0 + z1 + z2 + sum(S) + sb0 + sb1 + sb2 */
  ssum = RH_R(0.0);
  for (k = 0; k < 9; k++) ssum += S[k];
  tot = z0 + z1 + z2 + ssum + sb[0] + sb[1] + sb[2];
  if (!RH_FINITE(tot)) {
    rh_substep_fail(xn, A, B);
    return;
  }
  if (xn != 0) {
    xn[0] = z0;
    xn[1] = z1;
    xn[2] = z2;
  }
  for (k = 0; k < 9; k++) A[k] = S[k];
  for (k = 0; k < 3; k++) B[k] = sb[k];
}
