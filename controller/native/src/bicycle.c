/* Linear 2-DoF bicycle prediction model (see bicycle.h). Operation order follows
 * controller/core/model/bicycle.py (_rhs for predict, _rhs_jac for predict_linearize). */
#include "bicycle.h"

#include "substep.h"

#define V_LOW RH_R(RH_SUBSTEP_V_LOW_MPS) /* m/s */

/* Per-call constants (reference _prepare). */
typedef struct {
  const rh_bicycle_t *m;
  real_t delta;   /* road-wheel angle, rad */
  real_t ax;      /* Tt / (m R), m/s^2 */
  real_t dm_term; /* kdm DeltaM, rad/s^2 */
} bicycle_call_t;

void rh_bicycle_init(rh_bicycle_t *m, const rh_vehicle_t *p, double h_max_s) {
  m->h_max_s = h_max_s;
  m->stiff_rate = rh_substep_stiffness_rate(p->cf_axle_n_per_rad, p->cr_axle_n_per_rad,
                                            p->mass_kg, p->yaw_inertia_kgm2, p->lf_m, p->lr_m);
  m->m = (real_t)p->mass_kg;
  m->iz = (real_t)p->yaw_inertia_kgm2;
  m->lf = (real_t)p->lf_m;
  m->lr = (real_t)p->lr_m;
  m->cf = (real_t)p->cf_axle_n_per_rad;
  m->cr = (real_t)p->cr_axle_n_per_rad;
  m->kdm = (real_t)(p->track_m / (2.0 * p->wheel_radius_m * p->yaw_inertia_kgm2));
  m->radius = (real_t)p->wheel_radius_m;
}

size_t rh_bicycle_sizeof(void) { return sizeof(rh_bicycle_t); }

static void prepare(const rh_bicycle_t *m, const rh_ctx_t *ctx, real_t dm, bicycle_call_t *c) {
  c->m = m;
  c->delta = ctx->delta_w;
  c->ax = ctx->total_torque / (m->m * m->radius);
  c->dm_term = m->kdm * dm;
}

static void rhs(const void *call, real_t vx, real_t vy, real_t r, real_t g[3]) {
  const bicycle_call_t *c = (const bicycle_call_t *)call;
  const rh_bicycle_t *m = c->m;
  real_t den, steer, fyf, fyr;
  if (vx > V_LOW || vx < -V_LOW) {
    den = RH_FABS(vx);
    steer = c->delta;
  } else {
    den = V_LOW;
    steer = c->delta * RH_FABS(vx) / V_LOW;
  }
  fyf = m->cf * ((vy + m->lf * r) / den - steer); /* N */
  fyr = m->cr * ((vy - m->lr * r) / den);         /* N */
  g[0] = c->ax;
  g[1] = (fyf + fyr) / m->m - vx * r;
  g[2] = (m->lf * fyf - m->lr * fyr) / m->iz + c->dm_term;
}

static void rhs_jac(const void *call, real_t vx, real_t vy, real_t r, real_t g[15]) {
  const bicycle_call_t *c = (const bicycle_call_t *)call;
  const rh_bicycle_t *mo = c->m;
  real_t m = mo->m, iz = mo->iz, lf = mo->lf, lr = mo->lr, cf = mo->cf, cr = mo->cr;
  real_t d = c->delta;
  real_t den, dden, steer, dsteer, inv, af, ar, fyf, fyr, dfyf_vx, dfyr_vx;
  if (vx > V_LOW) {
    den = vx; dden = RH_R(1.0); steer = d; dsteer = RH_R(0.0);
  } else if (vx < -V_LOW) {
    den = -vx; dden = RH_R(-1.0); steer = d; dsteer = RH_R(0.0);
  } else {
    real_t sgn = vx >= RH_R(0.0) ? RH_R(1.0) : RH_R(-1.0);
    den = V_LOW; dden = RH_R(0.0);
    steer = d * sgn * vx / V_LOW;
    dsteer = d * sgn / V_LOW;
  }
  inv = RH_R(1.0) / den; /* s/m */
  af = (vy + lf * r) * inv - steer; /* rad */
  ar = (vy - lr * r) * inv;         /* rad */
  fyf = cf * af;                    /* N */
  fyr = cr * ar;                    /* N */
  /* dFy/dvx through the 1/den of the slip angle (and the low-speed steering fade), N s/m */
  dfyf_vx = -cf * ((vy + lf * r) * inv * inv * dden + dsteer);
  dfyr_vx = -cr * (vy - lr * r) * inv * inv * dden;
  g[0] = c->ax;
  g[1] = (fyf + fyr) / m - vx * r;
  g[2] = (lf * fyf - lr * fyr) / iz + c->dm_term;
  g[3] = RH_R(0.0);
  g[4] = RH_R(0.0);
  g[5] = RH_R(0.0);
  g[6] = (dfyf_vx + dfyr_vx) / m - r;
  g[7] = (cf + cr) * inv / m;
  g[8] = (cf * lf - cr * lr) * inv / m - vx;
  g[9] = (lf * dfyf_vx - lr * dfyr_vx) / iz;
  g[10] = (lf * cf - lr * cr) * inv / iz;
  g[11] = (lf * lf * cf + lr * lr * cr) * inv / iz;
  g[12] = RH_R(0.0);
  g[13] = RH_R(0.0);
  g[14] = mo->kdm;
}

void rh_bicycle_predict(const rh_bicycle_t *m, const real_t x[3], real_t dm,
                        const rh_ctx_t *ctx, real_t xn[3]) {
  bicycle_call_t c;
  int n = rh_substep_count(x, dm, ctx, m->h_max_s, m->stiff_rate);
  if (n == 0) {
    xn[0] = (real_t)NAN; xn[1] = (real_t)NAN; xn[2] = (real_t)NAN;
    return;
  }
  prepare(m, ctx, dm, &c);
  rh_substep_predict(rhs, &c, n, ctx->ts, x, xn);
}

void rh_bicycle_predict_linearize(const rh_bicycle_t *m, const real_t x[3], real_t dm,
                                  const rh_ctx_t *ctx, real_t xn[3], real_t A[9],
                                  real_t B[3]) {
  bicycle_call_t c;
  int n = rh_substep_count(x, dm, ctx, m->h_max_s, m->stiff_rate);
  if (n == 0) {
    rh_substep_fail(xn, A, B);
    return;
  }
  prepare(m, ctx, dm, &c);
  rh_substep_propagate(rhs_jac, &c, n, ctx->ts, x, xn, A, B);
}
