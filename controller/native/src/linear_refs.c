/* Linear steady-state references (see linear_refs.h). Operation order follows
 * controller/core/references/linear.py. */
#include "linear_refs.h"

void rh_linear_refs_init(rh_linear_refs_t *s, const rh_vehicle_t *p) {
  double cf = fabs(p->cf_axle_n_per_rad), cr = fabs(p->cr_axle_n_per_rad); /* N/rad */
  double L = p->lf_m + p->lr_m;                                            /* m */
  double K = p->mass_kg / (L * L) * (p->lr_m / cf - p->lf_m / cr);         /* s^2/m^2 */
  s->critical_speed_mps = K < 0.0 ? 1.0 / sqrt(-K) : HUGE_VAL;
  s->guard_speed_mps = K < 0.0 ? sqrt((1.0 - RH_LINEAR_REFS_DEN_MIN) / -K) : HUGE_VAL;
  s->wheelbase = (real_t)L;
  s->understeer_gradient = (real_t)K;
  s->lr = (real_t)p->lr_m;
  s->beta_k = (real_t)(p->mass_kg * p->lf_m / (L * cr));
}

void rh_linear_refs_reset(rh_linear_refs_t *s) { (void)s; }

size_t rh_linear_refs_sizeof(void) { return sizeof(rh_linear_refs_t); }

void rh_linear_refs_compute(const rh_linear_refs_t *s, real_t vx, real_t vy, real_t yaw_rate,
                            real_t delta_w, real_t total_torque, real_t ay_meas,
                            real_t out[3]) {
  const real_t max_steer = (real_t)(0.5 * 3.14159265358979323846); /* pi/2, rad */
  real_t v2, den, L, r_ss, beta_ss;
  (void)vy;
  (void)yaw_rate;
  (void)total_torque;
  (void)ay_meas;
  /* written so that NaN fails the test, as the reference's not (a <= b and c <= d) */
  if (!(RH_FABS(vx) <= RH_R(RH_LINEAR_REFS_MAX_SPEED_MPS) && RH_FABS(delta_w) <= max_steer)) {
    out[0] = RH_R(0.0); out[1] = RH_R(0.0); out[2] = RH_R(0.0);
    return;
  }
  v2 = vx * vx;                                  /* m^2/s^2 */
  den = RH_R(1.0) + s->understeer_gradient * v2; /* - */
  if (den < RH_R(RH_LINEAR_REFS_DEN_MIN)) den = RH_R(RH_LINEAR_REFS_DEN_MIN);
  L = s->wheelbase;
  r_ss = vx * delta_w / (L * den);
  beta_ss = delta_w * (s->lr - s->beta_k * v2) / (L * den);
  out[0] = r_ss;
  out[1] = beta_ss * vx;
  out[2] = beta_ss;
}
