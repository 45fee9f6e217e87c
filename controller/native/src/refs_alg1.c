/* Algorithm 1 references (see refs_alg1.h). Operation order follows the numpy reference
 * (algorithm1.py _grid/_newton/compute), so the float64 build agrees to rounding. */
#include "refs_alg1.h"

int rh_refs_alg1_init(rh_refs_alg1_t *a, const rh_refs_config_t *cfg, const rh_vehicle_t *p) {
  int i, n = cfg->grid_n;
  double step;
  if (n < 3 || n % 2 == 0 || n > RH_REFS_GRID_MAX) return RH_REFS_EGRID;
  if (cfg->max_rounds < 0 || cfg->max_rounds > RH_REFS_ROUNDS_MAX) return RH_REFS_EROUNDS;
  if (cfg->newton_iters < 0 || cfg->newton_iters > RH_REFS_NEWTON_MAX) return RH_REFS_ENEWTON;
  if (!(cfg->ts > 0.0) || !(cfg->ay_decay_s > 0.0)) return RH_REFS_ETIME;
  a->eta = (real_t)cfg->eta;
  a->eps_t = (real_t)cfg->eps_t;
  a->rs0_vy = (real_t)cfg->rs0_vy;
  a->rs0_r = (real_t)cfg->rs0_r;
  a->drs_vy = (real_t)cfg->drs_vy;
  a->drs_r = (real_t)cfg->drs_r;
  a->tan_beta_max = (real_t)cfg->tan_beta_max;
  a->ay_floor = (real_t)cfg->ay_floor;
  a->ay_ceiling = (real_t)cfg->ay_ceiling;
  a->ay_margin = (real_t)cfg->ay_margin;
  a->decay = (real_t)exp(-cfg->ts / cfg->ay_decay_s);
  a->v_min = (real_t)cfg->v_min;
  a->r_kin_factor = (real_t)cfg->r_kin_factor;
  a->r_band = (real_t)cfg->r_band;
  a->wheelbase_m = (real_t)(p->lf_m + p->lr_m);
  a->lr_m = (real_t)p->lr_m;
  /* numpy.linspace(-1, 1, n): i * step + start, last node = stop */
  step = 2.0 / (double)(n - 1);
  for (i = 0; i < RH_REFS_GRID_MAX; i++)
    a->unit[i] = (real_t)(i < n ? (i == n - 1 ? 1.0 : (double)i * step + -1.0) : 0.0);
  a->grid_n = n;
  a->max_rounds = cfg->max_rounds;
  a->newton_iters = cfg->newton_iters;
  rh_slow_weights_init(&a->weights, cfg->slow_tau_s, cfg->ts);
  rh_refs_alg1_reset(a);
  return RH_REFS_OK;
}

void rh_refs_alg1_reset(rh_refs_alg1_t *a) {
  rh_slow_weights_reset(&a->weights);
  a->ay_envelope = RH_R(0.0);
  a->not_converged = 0;
  a->rounds_last = 0;
  a->cost_last = RH_R(0.0);
}

/* Search constants of one compute() call. */
typedef struct {
  const real_t *C;  /* bilinear coefficients (3, 4) */
  real_t mu1, be1;  /* S(Vy): mu -, beta 1/(m/s) */
  real_t mu2, be2;  /* S(wr): mu -, beta 1/(rad/s) */
  int inc;          /* increment form */
} alg1_map_t;

/* Fixed-point residuals (F_vy - Vy m/s, F_r - wr rad/s) at (vy m/s, r rad/s). */
static void residual(const alg1_map_t *mp, real_t vy, real_t r, real_t *gv, real_t *gr) {
  const real_t *C = mp->C;
  real_t a = mp->mu1 * RH_TANH(mp->be1 * vy);
  real_t b = mp->mu2 * RH_TANH(mp->be2 * r);
  real_t v = C[4] + C[5] * a + C[6] * b + C[7] * a * b;
  real_t w = C[8] + C[9] * a + C[10] * b + C[11] * a * b;
  if (!mp->inc) {
    v -= vy;
    w -= r;
  }
  *gv = v;
  *gr = w;
}

/* Cost over the n x n grid on [lo_v, hi_v] x [lo_r, hi_r]; selection minimises
 * cost + eps_t d^2 (d: distance to (cv, cr) in radii (rv, rr)), first minimum in row-major
 * order as np.argmin (a NaN wins at its first occurrence). Returns the node and its cost. */
static void grid(const rh_refs_alg1_t *a, const alg1_map_t *mp, real_t lo_v, real_t hi_v,
                 real_t lo_r, real_t hi_r, real_t cv, real_t cr, real_t rv, real_t rr,
                 real_t *bv, real_t *br, real_t *bc) {
  real_t nv[RH_REFS_GRID_MAX], nr[RH_REFS_GRID_MAX], xa[RH_REFS_GRID_MAX],
      xb[RH_REFS_GRID_MAX];
  const real_t *C = mp->C;
  const int n = a->grid_n;
  real_t hv = RH_R(0.5) * (hi_v - lo_v), hr = RH_R(0.5) * (hi_r - lo_r);
  real_t mv = lo_v + hv, mr = lo_r + hr;
  real_t irv = RH_R(1.0) / rv, irr = RH_R(1.0) / rr;
  real_t best = (real_t)INFINITY, bcost = (real_t)NAN;
  int i, j, bi = 0, bj = 0, found_nan = 0;
  for (i = 0; i < RH_REFS_GRID_MAX && i < n; i++) {
    nv[i] = a->unit[i] * hv + mv;
    nr[i] = a->unit[i] * hr + mr;
    xa[i] = RH_TANH(nv[i] * mp->be1) * mp->mu1;
    xb[i] = RH_TANH(nr[i] * mp->be2) * mp->mu2;
  }
  for (i = 0; i < RH_REFS_GRID_MAX && i < n && !found_nan; i++) {
    real_t x = xa[i];
    real_t t2v = C[7] * x + C[6], t2r = C[11] * x + C[10];
    real_t t1v = C[5] * x + C[4], t1r = C[9] * x + C[8];
    real_t dv = (nv[i] - cv) * irv;
    dv = dv * dv;
    for (j = 0; j < RH_REFS_GRID_MAX && j < n; j++) {
      real_t g0 = t2v * xb[j] + t1v, g1 = t2r * xb[j] + t1r, cost, dr, sel;
      if (!mp->inc) {
        g0 -= nv[i];
        g1 -= nr[j];
      }
      cost = RH_FABS(g0) + RH_FABS(g1) * a->eta;
      dr = (nr[j] - cr) * irr;
      sel = (dv + dr * dr) * a->eps_t + cost;
      if (sel != sel) { /* np.argmin: the first NaN */
        bi = i;
        bj = j;
        bcost = cost;
        found_nan = 1;
        break;
      }
      if (sel < best) {
        best = sel;
        bi = i;
        bj = j;
        bcost = cost;
      }
    }
  }
  if (!found_nan && best == (real_t)INFINITY) { /* all +inf: np.argmin's first node */
    real_t g0 = (C[7] * xa[0] + C[6]) * xb[0] + (C[5] * xa[0] + C[4]);
    real_t g1 = (C[11] * xa[0] + C[10]) * xb[0] + (C[9] * xa[0] + C[8]);
    if (!mp->inc) {
      g0 -= nv[0];
      g1 -= nr[0];
    }
    bcost = RH_FABS(g0) + RH_FABS(g1) * a->eta;
  }
  *bv = nv[bi];
  *br = nr[bj];
  *bc = bcost;
}

/* <= newton_iters damped Newton steps on the 2x2 fixed-point equations inside the box,
 * accepted only while the cost decreases (RhonnReferences._newton). */
static void newton(const rh_refs_alg1_t *a, const alg1_map_t *mp, real_t *pvy, real_t *pr,
                   real_t *pcost, real_t lo_v, real_t hi_v, real_t lo_r, real_t hi_r) {
  const real_t *C = mp->C;
  real_t vy = *pvy, r = *pr, cost = *pcost;
  int it;
  for (it = 0; it < RH_REFS_NEWTON_MAX && it < a->newton_iters; it++) {
    real_t gv, gr, ta, tb, xa, xb, da, db, j11, j12, j21, j22, det, nv, nr, ngv, ngr, ncost;
    residual(mp, vy, r, &gv, &gr);
    ta = RH_TANH(mp->be1 * vy);
    tb = RH_TANH(mp->be2 * r);
    xa = mp->mu1 * ta;
    xb = mp->mu2 * tb;
    da = mp->mu1 * mp->be1 * (RH_R(1.0) - ta * ta);
    db = mp->mu2 * mp->be2 * (RH_R(1.0) - tb * tb);
    j11 = (C[5] + C[7] * xb) * da;
    j12 = (C[6] + C[7] * xa) * db;
    j21 = (C[9] + C[11] * xb) * da;
    j22 = (C[10] + C[11] * xa) * db;
    if (!mp->inc) {
      j11 -= RH_R(1.0);
      j22 -= RH_R(1.0);
    }
    det = j11 * j22 - j12 * j21;
    if (!RH_FINITE(det) || RH_FABS(det) < RH_R(1e-12)) break;
    nv = rh_refs_pymin(rh_refs_pymax(vy - (j22 * gv - j12 * gr) / det, lo_v), hi_v);
    nr = rh_refs_pymin(rh_refs_pymax(r - (j11 * gr - j21 * gv) / det, lo_r), hi_r);
    residual(mp, nv, nr, &ngv, &ngr);
    ncost = RH_FABS(ngv) + a->eta * RH_FABS(ngr);
    if (!(ncost < cost)) break;
    vy = nv;
    r = nr;
    cost = ncost;
    if (cost <= a->eps_t) break;
  }
  *pvy = vy;
  *pr = r;
  *pcost = cost;
}

void rh_refs_alg1_compute(rh_refs_alg1_t *a, const rh_rhonn_view_t *m, real_t vx, real_t vy,
                          real_t yaw_rate, real_t delta_w, real_t ay_meas, real_t out[3]) {
  real_t C[12];
  alg1_map_t mp;
  real_t r_lim, v_lim, r_kin, r_lo, r_hi, cv, cr, bv, br, bc;
  int k, rounds = 0, converged_or_stopped = 0;
  if (RH_FINITE(ay_meas))
    a->ay_envelope = rh_refs_pymax(RH_FABS(ay_meas), a->ay_envelope * a->decay);
  rh_slow_weights_update(&a->weights, m->W);
  if (!(RH_FINITE(vx) && RH_FINITE(delta_w))) {
    out[0] = RH_R(0.0); out[1] = RH_R(0.0); out[2] = RH_R(0.0);
    return;
  }
  if (!RH_FINITE(vy)) vy = RH_R(0.0);
  if (!RH_FINITE(yaw_rate)) yaw_rate = RH_R(0.0);
  if (vx < a->v_min) { /* kinematic */
    real_t v = rh_refs_pymax(vx, RH_R(0.0));
    real_t r_d = v * delta_w / a->wheelbase_m;
    real_t vy_d = a->lr_m * r_d;
    out[0] = r_d;
    out[1] = vy_d;
    out[2] = vy_d / a->v_min;
    return;
  }
  /* a_max = clip(margin * envelope, floor, ceiling), m/s^2; |wr| <= a_max / Vx */
  r_lim = rh_refs_pymin(rh_refs_pymax(a->ay_margin * a->ay_envelope, a->ay_floor),
                        a->ay_ceiling) / vx;
  v_lim = a->tan_beta_max * vx;
  r_kin = a->r_kin_factor * vx * delta_w / a->wheelbase_m;
  r_lo = rh_refs_pymax(rh_refs_pymin(r_kin, RH_R(0.0)) - a->r_band, -r_lim);
  r_hi = rh_refs_pymin(rh_refs_pymax(r_kin, RH_R(0.0)) + a->r_band, r_lim);
  rh_slow_weights_coefficients(&a->weights, m, vx, delta_w, C);
  mp.C = C;
  mp.mu1 = m->mu[1];
  mp.be1 = m->beta[1];
  mp.mu2 = m->mu[2];
  mp.be2 = m->beta[2];
  mp.inc = m->increment;
  cv = rh_refs_pymin(rh_refs_pymax(vy, -v_lim), v_lim);
  cr = rh_refs_pymin(rh_refs_pymax(yaw_rate, r_lo), r_hi);
  bv = cv;
  br = cr;
  bc = (real_t)INFINITY;
  for (k = 0; k < RH_REFS_ROUNDS_MAX && k < a->max_rounds; k++) {
    real_t rv = a->rs0_vy + (real_t)k * a->drs_vy;
    real_t rr = a->rs0_r + (real_t)k * a->drs_r;
    real_t lo_v = rh_refs_pymax(cv - rv, -v_lim), hi_v = rh_refs_pymin(cv + rv, v_lim);
    real_t lo_r = rh_refs_pymax(cr - rr, r_lo), hi_r = rh_refs_pymin(cr + rr, r_hi);
    real_t gvy, gr, gcost;
    rounds = k + 1;
    grid(a, &mp, lo_v, hi_v, lo_r, hi_r, cv, cr, rv, rr, &gvy, &gr, &gcost);
    newton(a, &mp, &gvy, &gr, &gcost, lo_v, hi_v, lo_r, hi_r);
    if (gcost < bc) {
      bv = gvy;
      br = gr;
      bc = gcost;
    }
    if (bc <= a->eps_t) {
      converged_or_stopped = 1;
      break;
    }
    if (lo_v <= -v_lim && hi_v >= v_lim && lo_r <= r_lo && hi_r >= r_hi) {
      /* the whole feasible box was searched: growing the radius cannot help */
      a->not_converged += 1;
      converged_or_stopped = 1;
      break;
    }
  }
  if (!converged_or_stopped) a->not_converged += 1; /* for-else: rounds exhausted */
  a->rounds_last = rounds;
  a->cost_last = bc;
  if (!(RH_FINITE(bv) && RH_FINITE(br))) {
    bv = cv;
    br = cr;
  }
  out[0] = br;
  out[1] = bv;
  out[2] = bv / vx;
}
