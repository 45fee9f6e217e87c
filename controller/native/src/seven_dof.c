/* Quasi-steady-slip 7-DoF prediction model (see seven_dof.h). Operation order follows
 * controller/core/model/seven_dof.py (_prepare, _rhs for predict, _rhs_jac for
 * predict_linearize) and chassis.make_corners. */
#include "seven_dof.h"

#include "substep.h"

#define V_LOW RH_R(RH_SUBSTEP_V_LOW_MPS) /* m/s */
#define FZ_MIN RH_R(RH_MF_FZ_MIN_N)      /* N */

/* Per-call, per-wheel constants (reference _call[i]). */
typedef struct {
  real_t uw[3]; /* wheel-frame longitudinal speed u_w = uw . (vx, vy, r), m/s */
  real_t vw[3]; /* wheel-frame lateral speed v_w = vw . (vx, vy, r), m/s */
  real_t cx;    /* SUM FX per Fy, - */
  real_t cy;    /* SUM FY per Fy, - */
  real_t cm;    /* Mz per Fy, m */
  real_t fzb;   /* load without the lateral transfer, N */
} wheel_call_t;

/* Per-call constants (reference _prepare). */
typedef struct {
  const rh_seven_dof_t *m;
  real_t base[3]; /* (SUM FX N, SUM FY N, Mz N m) of the quasi-steady Fx */
  real_t dm[3];   /* their d/dDeltaM, (1/m, 1/m, -) */
  wheel_call_t w[4];
} seven_call_t;

void rh_seven_dof_init(rh_seven_dof_t *m, const rh_vehicle_t *p,
                       const rh_seven_dof_config_t *cfg) {
  const double G = RH_SEVEN_DOF_G_MPS2;
  double L = p->lf_m + p->lr_m;  /* wheelbase, m */
  double tw = 0.5 * p->track_m;  /* half track, m */
  double mass = p->mass_kg, h = p->cg_height_m;
  double fzf = mass * G * p->lr_m / (2.0 * L); /* static load per front wheel, N */
  double fzr = mass * G * p->lf_m / (2.0 * L); /* per rear wheel, N */
  double kx = mass * h / (2.0 * L);            /* N/(m/s^2) */
  double kyf = mass * h / p->track_m * p->lr_m / L;
  double kyr = mass * h / p->track_m * p->lf_m / L;
  double cf = -0.5 * p->cf_axle_n_per_rad; /* positive per-wheel stiffness, N/rad */
  double cr = -0.5 * p->cr_axle_n_per_rad;
  double fz_max = mass * G; /* N */
  /* corners FL, FR, RL, RR: x, y, front, Fz static, kx_ax, ky_ay, c_lin */
  const double cx_[4] = {p->lf_m, p->lf_m, -p->lr_m, -p->lr_m};
  const double cy_[4] = {tw, -tw, tw, -tw};
  const int cfront[4] = {1, 1, 0, 0};
  const double cfz[4] = {fzf, fzf, fzr, fzr};
  const double ckx[4] = {-kx, -kx, kx, kx};
  const double cky[4] = {-kyf, kyf, -kyr, kyr};
  const double ccl[4] = {cf, cf, cr, cr};
  int i;
  m->h_max_s = cfg->h_max_s;
  m->stiff_rate = rh_substep_stiffness_rate(p->cf_axle_n_per_rad, p->cr_axle_n_per_rad,
                                            p->mass_kg, p->yaw_inertia_kgm2, p->lf_m, p->lr_m);
  m->m = (real_t)mass;
  m->iz = (real_t)p->yaw_inertia_kgm2;
  m->radius = (real_t)p->wheel_radius_m;
  m->mu = (real_t)cfg->mu_nominal;
  m->rr = (real_t)(cfg->rolling_coeff * G);
  m->rr_ramp = (real_t)cfg->ramp_speed_mps;
  m->kd = (real_t)(cfg->drag_n_per_mps2 / mass);
  m->mf = cfg->linear ? 0 : 1;
  for (i = 0; i < 4; i++) {
    const rh_mf_curve_config_t *cv = cfront[i] ? &cfg->front_lateral : &cfg->rear_lateral;
    double cap = rh_mf_fz_cap(cv);
    rh_seven_dof_wheel_t *w = &m->w[i];
    if (fz_max < cap) cap = fz_max;
    w->x = (real_t)cx_[i];
    w->y = (real_t)cy_[i];
    w->fz_static = (real_t)cfz[i];
    w->kx_ax = (real_t)ckx[i];
    w->ky_ay = (real_t)cky[i];
    w->c_lin = (real_t)ccl[i];
    w->side = cy_[i] < 0.0 ? RH_R(1.0) : RH_R(-1.0);
    w->fz_cap = (real_t)cap;
    w->front = cfront[i];
    rh_mf_curve_init(&w->lateral, cv);
  }
}

size_t rh_seven_dof_sizeof(void) { return sizeof(rh_seven_dof_t); }

static void prepare(const rh_seven_dof_t *m, const rh_ctx_t *ctx, real_t dm, seven_call_t *c) {
  real_t d = ctx->delta_w;
  real_t cd = RH_COS(d), sd = RH_SIN(d);
  real_t tt = ctx->total_torque;
  real_t ax = tt / (m->m * m->radius);                 /* m/s^2 */
  real_t fx_mean = tt / (RH_R(4.0) * m->radius);       /* N per wheel from Tt */
  real_t fx_dm = dm / (RH_R(4.0) * m->radius);         /* N per wheel from DeltaM */
  real_t fdm = RH_R(1.0) / (RH_R(4.0) * m->radius);    /* 1/m */
  real_t bx = RH_R(0.0), by = RH_R(0.0), bm = RH_R(0.0);
  real_t dx = RH_R(0.0), dy = RH_R(0.0), dmz = RH_R(0.0);
  int i;
  c->m = m;
  for (i = 0; i < 4; i++) {
    const rh_seven_dof_wheel_t *w = &m->w[i];
    wheel_call_t *wc = &c->w[i];
    real_t xw = w->x, yw = w->y, side = w->side;
    real_t fx = fx_mean + side * fx_dm; /* N */
    real_t fX, fY, gX, gY;
    if (w->front) {
      /* u_w = cd u + sd v, v_w = cd v - sd u with u = vx - y r, v = vy + x r */
      wc->uw[0] = cd; wc->uw[1] = sd; wc->uw[2] = -yw * cd + xw * sd;
      wc->vw[0] = -sd; wc->vw[1] = cd; wc->vw[2] = xw * cd + yw * sd;
      wc->cx = -sd; wc->cy = cd; wc->cm = xw * cd + yw * sd;
      fX = fx * cd; fY = fx * sd;
      gX = cd * side * fdm; gY = sd * side * fdm;
    } else {
      wc->uw[0] = RH_R(1.0); wc->uw[1] = RH_R(0.0); wc->uw[2] = -yw;
      wc->vw[0] = RH_R(0.0); wc->vw[1] = RH_R(1.0); wc->vw[2] = xw;
      wc->cx = RH_R(0.0); wc->cy = RH_R(1.0); wc->cm = xw;
      fX = fx; fY = RH_R(0.0);
      gX = side * fdm; gY = RH_R(0.0);
    }
    bx += fX;
    by += fY;
    bm += xw * fY - yw * fX;
    dx += gX;
    dy += gY;
    dmz += xw * gY - yw * gX;
    wc->fzb = w->fz_static + w->kx_ax * ax;
  }
  c->base[0] = bx; c->base[1] = by; c->base[2] = bm;
  c->dm[0] = dx; c->dm[1] = dy; c->dm[2] = dmz;
}

/* Driving resistances: res[0] = dvx/dt from rolling resistance + drag (m/s^2), res[1] its
 * d/dvx (1/s). */
static void resistance(const rh_seven_dof_t *m, real_t vx, real_t res[2]) {
  real_t avx = vx >= RH_R(0.0) ? vx : -vx;
  real_t s = vx / m->rr_ramp, ds;
  if (s > RH_R(1.0)) {
    s = RH_R(1.0); ds = RH_R(0.0);
  } else if (s < RH_R(-1.0)) {
    s = RH_R(-1.0); ds = RH_R(0.0);
  } else {
    ds = RH_R(1.0) / m->rr_ramp;
  }
  res[0] = -(m->rr * s + m->kd * vx * avx);
  res[1] = -(m->rr * ds + RH_R(2.0) * m->kd * avx);
}

static void rhs(const void *call, real_t vx, real_t vy, real_t r, real_t g[3]) {
  const seven_call_t *c = (const seven_call_t *)call;
  const rh_seven_dof_t *m = c->m;
  real_t mu = m->mu;
  real_t ay = vx * r; /* quasi-static lateral acceleration, m/s^2 */
  real_t sx = c->base[0], sy = c->base[1], mz = c->base[2];
  real_t res[2];
  int i;
  for (i = 0; i < 4; i++) {
    const wheel_call_t *wc = &c->w[i];
    const rh_seven_dof_wheel_t *w = &m->w[i];
    real_t uw = wc->uw[0] * vx + wc->uw[1] * vy + wc->uw[2] * r; /* m/s */
    real_t vw = wc->vw[0] * vx + wc->vw[1] * vy + wc->vw[2] * r; /* m/s */
    real_t den = uw > V_LOW ? uw : (uw < -V_LOW ? -uw : V_LOW);
    real_t alpha = RH_ATAN2(vw, den); /* rad */
    real_t fy;                        /* N */
    if (m->mf) {
      real_t fz = wc->fzb + w->ky_ay * ay;
      if (fz < FZ_MIN) fz = FZ_MIN;
      if (fz > w->fz_cap) fz = w->fz_cap;
      fy = -rh_mf_force(&w->lateral, alpha, fz, mu);
    } else {
      fy = -w->c_lin * alpha;
    }
    sx += wc->cx * fy;
    sy += wc->cy * fy;
    mz += wc->cm * fy;
  }
  resistance(m, vx, res);
  g[0] = sx / m->m + vy * r + res[0];
  g[1] = sy / m->m - vx * r;
  g[2] = mz / m->iz;
}

static void rhs_jac(const void *call, real_t vx, real_t vy, real_t r, real_t g[15]) {
  const seven_call_t *c = (const seven_call_t *)call;
  const rh_seven_dof_t *m = c->m;
  real_t mu = m->mu;
  real_t ay = vx * r;
  real_t sx = c->base[0], sy = c->base[1], mz = c->base[2];
  /* accumulated partials of SUM FX, SUM FY (N per state unit), Mz (N m per state unit) */
  real_t X0 = RH_R(0.0), X1 = RH_R(0.0), X2 = RH_R(0.0);
  real_t Y0 = RH_R(0.0), Y1 = RH_R(0.0), Y2 = RH_R(0.0);
  real_t M0 = RH_R(0.0), M1 = RH_R(0.0), M2 = RH_R(0.0);
  real_t im, iz, res[2];
  int i;
  for (i = 0; i < 4; i++) {
    const wheel_call_t *wc = &c->w[i];
    const rh_seven_dof_wheel_t *w = &m->w[i];
    real_t uw0 = wc->uw[0], uw1 = wc->uw[1], uw2 = wc->uw[2];
    real_t vw0 = wc->vw[0], vw1 = wc->vw[1], vw2 = wc->vw[2];
    real_t uw = uw0 * vx + uw1 * vy + uw2 * r;
    real_t vw = vw0 * vx + vw1 * vy + vw2 * r;
    real_t den, dden, alpha, q, a_v, a_u, fy, fy0, fy1, fy2;
    if (uw > V_LOW) {
      den = uw; dden = RH_R(1.0);
    } else if (uw < -V_LOW) {
      den = -uw; dden = RH_R(-1.0);
    } else {
      den = V_LOW; dden = RH_R(0.0);
    }
    alpha = RH_ATAN2(vw, den);
    q = RH_R(1.0) / (den * den + vw * vw);
    a_v = den * q;        /* dalpha/dv_w, s/m */
    a_u = -vw * q * dden; /* dalpha/du_w, s/m */
    if (m->mf) {
      real_t fz = wc->fzb + w->ky_ay * ay, ok = RH_R(1.0), mfo[3], kz;
      if (fz < FZ_MIN) {
        fz = FZ_MIN; ok = RH_R(0.0);
      } else if (fz > w->fz_cap) {
        fz = w->fz_cap; ok = RH_R(0.0);
      }
      rh_mf_eval(&w->lateral, alpha, fz, mu, mfo);
      fy = -mfo[0];
      kz = -mfo[2] * w->ky_ay * ok; /* dFy/day through the load (ay = vx r), kg */
      fy0 = -mfo[1] * (a_v * vw0 + a_u * uw0) + kz * r;
      fy1 = -mfo[1] * (a_v * vw1 + a_u * uw1);
      fy2 = -mfo[1] * (a_v * vw2 + a_u * uw2) + kz * vx;
    } else {
      real_t cl = w->c_lin;
      fy = -cl * alpha;
      fy0 = -cl * (a_v * vw0 + a_u * uw0);
      fy1 = -cl * (a_v * vw1 + a_u * uw1);
      fy2 = -cl * (a_v * vw2 + a_u * uw2);
    }
    sx += wc->cx * fy;
    sy += wc->cy * fy;
    mz += wc->cm * fy;
    X0 += wc->cx * fy0;
    X1 += wc->cx * fy1;
    X2 += wc->cx * fy2;
    Y0 += wc->cy * fy0;
    Y1 += wc->cy * fy1;
    Y2 += wc->cy * fy2;
    M0 += wc->cm * fy0;
    M1 += wc->cm * fy1;
    M2 += wc->cm * fy2;
  }
  im = RH_R(1.0) / m->m;  /* 1/kg */
  iz = RH_R(1.0) / m->iz; /* 1/(kg m^2) */
  resistance(m, vx, res);
  g[0] = sx * im + vy * r + res[0];
  g[1] = sy * im - vx * r;
  g[2] = mz * iz;
  g[3] = X0 * im + res[1];
  g[4] = X1 * im + r;
  g[5] = X2 * im + vy;
  g[6] = Y0 * im - r;
  g[7] = Y1 * im;
  g[8] = Y2 * im - vx;
  g[9] = M0 * iz;
  g[10] = M1 * iz;
  g[11] = M2 * iz;
  g[12] = c->dm[0] * im;
  g[13] = c->dm[1] * im;
  g[14] = c->dm[2] * iz;
}

void rh_seven_dof_predict(const rh_seven_dof_t *m, const real_t x[3], real_t dm,
                          const rh_ctx_t *ctx, real_t xn[3]) {
  seven_call_t c;
  int n = rh_substep_count(x, dm, ctx, m->h_max_s, m->stiff_rate);
  if (n == 0) {
    xn[0] = (real_t)NAN; xn[1] = (real_t)NAN; xn[2] = (real_t)NAN;
    return;
  }
  prepare(m, ctx, dm, &c);
  rh_substep_predict(rhs, &c, n, ctx->ts, x, xn);
}

void rh_seven_dof_predict_linearize(const rh_seven_dof_t *m, const real_t x[3], real_t dm,
                                    const rh_ctx_t *ctx, real_t xn[3], real_t A[9],
                                    real_t B[3]) {
  seven_call_t c;
  int n = rh_substep_count(x, dm, ctx, m->h_max_s, m->stiff_rate);
  if (n == 0) {
    rh_substep_fail(xn, A, B);
    return;
  }
  prepare(m, ctx, dm, &c);
  rh_substep_propagate(rhs_jac, &c, n, ctx->ts, x, xn, A, B);
}
