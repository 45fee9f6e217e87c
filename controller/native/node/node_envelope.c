/* Output safety envelope (see node_envelope.h; Python: SafetyEnvelope.apply). */
#include "node_envelope.h"

#include <math.h>
#include <string.h>

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }
/* Python's max(x, y) / min(x, y): the first argument unless the second is strictly
 * larger / smaller (the same signed zero and NaN outcome as the reference). */
static double pmax(double x, double y) { return y > x ? y : x; }
static double pmin(double x, double y) { return y < x ? y : x; }

void rh_node_envelope_default_config(rh_node_envelope_config_t *cfg) {
  cfg->torque_rate_nm_per_s = 60000.0;
  cfg->delta_m_rate_nm_per_s = 180000.0;
  cfg->torque_quantum_nm = 0.5;
  cfg->clip_tol_nm = 1e-6;
}

static int envelope_config_ok(const rh_node_envelope_config_t *c) {
  return isfinite(c->torque_rate_nm_per_s) && c->torque_rate_nm_per_s > 0.0 &&
         isfinite(c->delta_m_rate_nm_per_s) && c->delta_m_rate_nm_per_s > 0.0 &&
         isfinite(c->torque_quantum_nm) && c->torque_quantum_nm >= 0.0 &&
         isfinite(c->clip_tol_nm) && c->clip_tol_nm >= 0.0;
}

int rh_node_envelope_init(rh_node_envelope_t *e, const rh_node_envelope_config_t *cfg,
                          double peak_torque_nm, double peak_power_w, double dt_s) {
  int ok = cfg != NULL && envelope_config_ok(cfg) && peak_torque_nm > 0.0 && peak_power_w > 0.0 &&
           dt_s > 0.0 && isfinite(peak_torque_nm) && isfinite(peak_power_w) && isfinite(dt_s);
  int i;
  (void)memset(e, 0, sizeof *e);
  if (!ok) { /* safe state: every command clipped to 0 N m */
    rh_node_envelope_default_config(&e->cfg);
    return -1;
  }
  e->cfg = *cfg;
  e->t_peak = peak_torque_nm;
  e->p_peak = peak_power_w;
  e->dt = dt_s;
  e->d_wheel = cfg->torque_rate_nm_per_s * dt_s;
  e->d_dm = cfg->delta_m_rate_nm_per_s * dt_s;
  for (i = 0; i < 4; ++i) {
    e->limits[i] = e->t_peak;
  }
  return 0;
}

int rh_node_envelope_conflict_free(const rh_node_envelope_t *e) {
  return e->d_wheel >= e->t_peak && e->d_dm >= 4.0 * e->t_peak;
}

double rh_node_envelope_wheel_limit(const rh_node_envelope_t *e, double omega_rad_s) {
  double tp = e->t_peak, w, lim, q = e->cfg.torque_quantum_nm;
  if (!isfinite(omega_rad_s)) {
    return tp;
  }
  w = fabs(omega_rad_s);
  if (w * tp <= e->p_peak) { /* multiplication: no overflow for tiny w */
    return tp;
  }
  lim = e->p_peak / w;
  return q > 0.0 ? floor(lim / q) * q : lim;
}

/* Common window of wheels a and b; if their rate windows do not overlap, the symmetric
 * point nearest both (within the motor limits) wins: a counted conflict. */
static void pair_window(rh_node_envelope_t *e, int a, int b, double lo[4], double hi[4],
                        double *w_lo, double *w_hi) {
  double l = pmax(lo[a], lo[b]);
  double h = pmin(hi[a], hi[b]);
  double lim, x;
  if (l <= h) {
    *w_lo = l;
    *w_hi = h;
    return;
  }
  e->counters.conflicts += 1;
  lim = pmin(e->limits[a], e->limits[b]);
  x = clip(0.5 * (l + h), -lim, lim);
  lo[a] = x;
  lo[b] = x;
  hi[a] = x;
  hi[b] = x;
  *w_lo = x;
  *w_hi = x;
}

/* Zero Delta M: one torque per axle inside both wheels' windows, Tt kept if possible. */
static void symmetric(rh_node_envelope_t *e, const double cm[4], double lo[4], double hi[4],
                      double tt, double out[4]) {
  double f_lo, f_hi, r_lo, r_hi, f, r;
  pair_window(e, 0, 1, lo, hi, &f_lo, &f_hi);
  pair_window(e, 2, 3, lo, hi, &r_lo, &r_hi);
  f = clip(0.5 * (cm[0] + cm[1]), f_lo, f_hi);
  r = clip(0.5 * tt - f, r_lo, r_hi);
  f = clip(0.5 * tt - r, f_lo, f_hi); /* the front takes what the rear could not */
  out[0] = f;
  out[1] = f;
  out[2] = r;
  out[3] = r;
}

/* Wheels a, b summing to s within their windows, nearest to their commands in the
 * least-squares sense (an equal shift of both, then the window of each). */
static void side(double s, const double cm[4], const double lo[4], const double hi[4], int a,
                 int b, double out[4]) {
  double xa = clip(cm[a] + 0.5 * (s - cm[a] - cm[b]), lo[a], hi[a]);
  double xb = clip(s - xa, lo[b], hi[b]);
  xa = clip(s - xb, lo[a], hi[a]);
  out[a] = xa;
  out[b] = xb;
}

/* Delta M as close to dm_t as the windows allow, then Tt, then each wheel. */
static void lever(rh_node_envelope_t *e, const double cm[4], const double lo[4],
                  const double hi[4], double tt, double dm_target, double dm_lo,
                  double dm_hi, double out[4]) {
  double dm_t = dm_target;
  double lo_l = lo[0] + lo[2], hi_l = hi[0] + hi[2];
  double lo_r = lo[1] + lo[3], hi_r = hi[1] + hi[3];
  double dm_min = lo_r - hi_l, dm_max = hi_r - lo_l;
  double s_lo, s_hi, s_left, s_right;
  if (dm_t < dm_min || dm_t > dm_max) {
    dm_t = clip(dm_t, dm_min, dm_max);
    if (dm_t < dm_lo || dm_t > dm_hi) { /* the wheel windows win over the Delta-M rate */
      e->counters.conflicts += 1;
    }
  }
  s_lo = pmax(lo_l, lo_r - dm_t);
  s_hi = pmin(hi_l, hi_r - dm_t);
  if (s_lo > s_hi) { /* only by rounding at a corner */
    s_lo = 0.5 * (s_lo + s_hi);
    s_hi = s_lo;
  }
  s_left = clip(0.5 * (tt - dm_t), s_lo, s_hi);
  s_right = s_left + dm_t;
  side(s_left, cm, lo, hi, 0, 2, out);
  side(s_right, cm, lo, hi, 1, 3, out);
}

int rh_node_envelope_apply(rh_node_envelope_t *e, const double cmd[4],
                           const double wheel_speeds[4], int zero_dm, const double prev[4],
                           double out[4]) {
  rh_node_envelope_counters_t *c = &e->counters;
  double tp = e->t_peak, d = e->d_wheel;
  double cm[4], pv[4], lo[4], hi[4];
  double dm_prev, dm_c, tt_c, dm_lo, dm_hi;
  int i, acted = 0, fast = 1;
  c->steps += 1;
  for (i = 0; i < 4; ++i) {
    double w = wheel_speeds[i], L, p = prev[i], t = cmd[i], a, b;
    if (!isfinite(w)) {
      c->invalid_speed += 1;
    }
    L = rh_node_envelope_wheel_limit(e, w);
    e->limits[i] = L;
    if (!isfinite(p)) {
      c->bad_prev += 1;
      p = 0.0;
    } else if (fabs(p) > tp) {
      c->bad_prev += 1;
      p = copysign(tp, p);
    } else {
      /* a previous output inside T_peak is used as it is */
    }
    pv[i] = p;
    if (!isfinite(t)) {
      c->nonfinite_cmd += 1;
      t = 0.0;
      acted = 1;
    } else if (fabs(t) > tp) {
      c->torque_limit += 1;
      t = copysign(tp, t);
      acted = 1;
    } else if (fabs(t) > L) {
      c->power_limit += 1;
      acted = 1;
    } else {
      /* inside the motor limit: the command as it is */
    }
    cm[i] = t;
    a = pmax(-L, p - d);
    b = pmin(L, p + d);
    if (a > b) { /* rate window outside the motor limit: the motor limit wins */
      c->conflicts += 1;
      a = (p - d > L) ? L : -L;
      b = a;
    }
    lo[i] = a;
    hi[i] = b;
    if (t < a || t > b) {
      fast = 0;
      if (-L <= t && t <= L) {
        c->rate_limit += 1;
        acted = 1;
      }
    }
  }
  dm_prev = (pv[1] - pv[0]) + (pv[3] - pv[2]); /* per axle: exactly 0 when symmetric */
  dm_c = (cm[1] - cm[0]) + (cm[3] - cm[2]);
  tt_c = cm[0] + cm[1] + cm[2] + cm[3];
  e->last_zeroed = 0;
  dm_lo = dm_prev - e->d_dm;
  dm_hi = dm_prev + e->d_dm;
  if (zero_dm) {
    if (cm[0] != cm[1] || cm[2] != cm[3]) {
      fast = 0;
      c->dm_zeroed += 1;
      e->last_zeroed = 1;
    }
    if (fabs(dm_prev) > e->d_dm) { /* Delta M = 0 wins over its rate */
      c->conflicts += 1;
    }
  } else if (dm_c < dm_lo || dm_c > dm_hi) {
    fast = 0;
    c->dm_rate_limit += 1;
    acted = 1;
  } else {
    /* Delta M inside its rate window */
  }
  if (fast) {
    for (i = 0; i < 4; ++i) {
      out[i] = cm[i];
    }
  } else if (zero_dm) {
    symmetric(e, cm, lo, hi, tt_c, out);
  } else {
    lever(e, cm, lo, hi, tt_c, clip(dm_c, dm_lo, dm_hi), dm_lo, dm_hi, out);
  }
  if (fabs(out[0] + out[1] + out[2] + out[3] - tt_c) > e->cfg.clip_tol_nm) {
    c->tt_reduced += 1;
    acted = 1;
  }
  if (acted) {
    c->limited_steps += 1;
  }
  return acted;
}
