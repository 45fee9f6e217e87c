/* Torque allocation (see allocation.h; reference controller/core/allocation.py, whose
 * operation order this follows). */
#include "allocation.h"

void rh_alloc_init(rh_alloc_t *a, const rh_vehicle_t *veh, const rh_alloc_config_t *cfg) {
  double L = veh->lf_m + veh->lr_m; /* wheelbase, m */
  int i;
  a->peak_torque = (real_t)veh->peak_torque_nm;
  a->peak_power = (real_t)veh->peak_power_w;
  a->acc_clip = (real_t)cfg->acc_clip;
  a->mass = (real_t)veh->mass_kg;
  a->wheelbase = (real_t)L;
  a->cg_height = (real_t)veh->cg_height_m;
  a->track = (real_t)veh->track_m;
  a->lf = (real_t)veh->lf_m;
  a->lr = (real_t)veh->lr_m;
  a->fzf_static = (real_t)(veh->mass_kg * RH_ALLOC_G * veh->lr_m / L);
  a->fzr_static = (real_t)(veh->mass_kg * RH_ALLOC_G * veh->lf_m / L);
  a->fz_floor_frac = (real_t)cfg->fz_floor_frac;
  a->split = cfg->split == RH_ALLOC_SPLIT_EQUAL ? RH_ALLOC_SPLIT_EQUAL
                                                : RH_ALLOC_SPLIT_NORMAL_LOAD;
  for (i = 0; i < 4; i++) {
    a->limits[i] = a->peak_torque;
    a->out[i] = RH_R(0.0);
  }
  a->tt_applied = RH_R(0.0);
  a->dm_applied = RH_R(0.0);
  a->rate_step = (real_t)(veh->torque_rate_nm_per_s * cfg->cycle_s);
  rh_alloc_reset(a);
}

void rh_alloc_reset(rh_alloc_t *a) {
  int i;
  for (i = 0; i < 4; i++) {
    a->prev[i] = RH_R(0.0);
    a->out[i] = RH_R(0.0);
  }
  a->rate_limited_calls = 0;
}

static real_t min2(real_t x, real_t y) { return y < x ? y : x; }
static real_t max2(real_t x, real_t y) { return y > x ? y : x; }

void rh_alloc_motor_limits(rh_alloc_t *a, const real_t ws[4]) {
  int i;
  for (i = 0; i < 4; i++) {
    real_t w = RH_FABS(ws[i]);
    a->limits[i] = (RH_FINITE(w) && w > RH_R(0.0)) ? min2(a->peak_torque, a->peak_power / w)
                                                    : a->peak_torque;
  }
}

real_t rh_alloc_dm_capacity(rh_alloc_t *a, const real_t ws[4]) {
  rh_alloc_motor_limits(a, ws);
  return RH_R(2.0) * min2(a->limits[0] + a->limits[2], a->limits[1] + a->limits[3]);
}

void rh_alloc_front_share(const rh_alloc_t *a, real_t ax, real_t ay, real_t *sl, real_t *sr) {
  const real_t two = RH_R(2.0);
  real_t clip, axc, ayc, dlong, fzf, fzr, dlat, dlf, dlr, ff, fr, fz1, fz2, fz3, fz4;
  if (a->split == RH_ALLOC_SPLIT_EQUAL) {
    *sl = RH_R(0.5);
    *sr = RH_R(0.5);
    return;
  }
  clip = a->acc_clip;
  axc = RH_FINITE(ax) ? ax : RH_R(0.0);
  ayc = RH_FINITE(ay) ? ay : RH_R(0.0);
  axc = min2(max2(axc, -clip), clip);
  ayc = min2(max2(ayc, -clip), clip);
  dlong = a->mass * axc * a->cg_height / a->wheelbase; /* N, rear gains under +ax */
  fzf = a->fzf_static - dlong;
  fzr = a->fzr_static + dlong;
  dlat = a->mass * ayc * a->cg_height / a->track;      /* N, right gains under +ay */
  dlf = dlat * a->lr / a->wheelbase;
  dlr = dlat * a->lf / a->wheelbase;
  ff = a->fz_floor_frac * a->fzf_static / two;
  fr = a->fz_floor_frac * a->fzr_static / two;
  fz1 = max2(fzf / two - dlf / two, ff);
  fz2 = max2(fzf / two + dlf / two, ff);
  fz3 = max2(fzr / two - dlr / two, fr);
  fz4 = max2(fzr / two + dlr / two, fr);
  *sl = fz1 / (fz1 + fz3);
  *sr = fz2 / (fz2 + fz4);
}

/* Split a side torque front/rear by share, saturating one wheel into the other. */
static void split_side(real_t t_side, real_t front, real_t lim_f, real_t lim_r, real_t *tf_out,
                       real_t *tr_out) {
  real_t tf = t_side * front, tr;
  if (tf > lim_f)
    tf = lim_f;
  else if (tf < -lim_f)
    tf = -lim_f;
  tr = t_side - tf;
  if (tr > lim_r) {
    tr = lim_r;
    tf = t_side - tr;
  } else if (tr < -lim_r) {
    tr = -lim_r;
    tf = t_side - tr;
  }
  /* Final clamp only matters at the rounding level (|t_side| <= lim_f + lim_r). */
  tf = min2(max2(tf, -lim_f), lim_f);
  *tf_out = tf;
  *tr_out = tr;
}

void rh_alloc_allocate(rh_alloc_t *a, real_t tt, real_t dm, real_t ax, real_t ay,
                       const real_t ws[4], int limits_current, real_t torques[4]) {
  const real_t two = RH_R(2.0), half = RH_R(0.5);
  real_t cl, cr, tt_lo, tt_hi, t_left, t_right, sl, sr;
  int i;
  if (!limits_current) rh_alloc_motor_limits(a, ws);
  cl = a->limits[0] + a->limits[2];
  cr = a->limits[1] + a->limits[3];
  if (!RH_FINITE(dm)) dm = RH_R(0.0);
  if (!RH_FINITE(tt)) tt = RH_R(0.0);
  dm = min2(max2(dm, -(cl + cr)), cl + cr);
  tt_lo = max2(-two * cr - dm, dm - two * cl);
  tt_hi = min2(two * cr - dm, dm + two * cl);
  tt = min2(max2(tt, tt_lo), tt_hi);
  t_left = half * (tt - dm);
  t_right = half * (tt + dm);
  /* Rounding can put a side a hair over capacity at the corners; clamp it. */
  t_left = min2(max2(t_left, -cl), cl);
  t_right = min2(max2(t_right, -cr), cr);
  rh_alloc_front_share(a, ax, ay, &sl, &sr);
  split_side(t_left, sl, a->limits[0], a->limits[2], &a->out[0], &a->out[2]);
  split_side(t_right, sr, a->limits[1], a->limits[3], &a->out[1], &a->out[3]);
  if (a->rate_step > RH_R(0.0)) {
    int held = 0;
    for (i = 0; i < 4; i++) {
      /* the motor limit first: a wheel over a limit that fell is cut at once */
      real_t lim = a->limits[i];
      real_t lo = min2(max2(a->prev[i] - a->rate_step, -lim), lim);
      real_t hi = max2(min2(a->prev[i] + a->rate_step, lim), -lim);
      real_t v = a->out[i];
      if (v > hi) {
        a->out[i] = hi;
        held = 1;
      } else if (v < lo) {
        a->out[i] = lo;
        held = 1;
      }
      a->prev[i] = a->out[i];
    }
    if (held) {
      a->rate_limited_calls += 1;
      t_left = a->out[0] + a->out[2];
      t_right = a->out[1] + a->out[3];
    }
  }
  a->tt_applied = t_left + t_right;
  a->dm_applied = t_right - t_left;
  if (torques != a->out)
    for (i = 0; i < 4; i++) torques[i] = a->out[i];
}

void rh_alloc_sizes(int out[3]) {
  out[0] = (int)sizeof(rh_alloc_t);
  out[1] = (int)sizeof(rh_alloc_config_t);
  out[2] = (int)sizeof(rh_vehicle_t);
}
