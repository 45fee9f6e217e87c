/* Simplified pure-slip Magic Formula of the controller's 7-DoF models
 * (Python reference: controller/core/model/tyre.py, mf_eval / mf_force).
 *
 *   dfz = (Fz - Fz0) / Fz0
 *   D   = mu Fz (d1 + d2 dfz)              peak force, N
 *   K   = Fz (k1 + k2 dfz) exp(k3 dfz)     slip stiffness B C D, N/rad (or N per unit slip)
 *   E   = min(e1 + e2 dfz, 1)              curvature, -
 *   B   = K / (C D)                        stiffness factor, 1/rad
 *   F   = D sin(C atan(B s - E (B s - atan(B s))))
 * F is the positive curve (odd, increasing near 0); the lateral tyre force is Fy = -F(alpha).
 * No grip (D <= 1e-9 N) or a non-physical fit (K <= 0) gives F = 0 and zero derivatives. */
#ifndef RH_MF_TYRE_H
#define RH_MF_TYRE_H

#include "rh_real.h"

#define RH_MF_FZ_MIN_N 50.0      /* normal-load floor, N (lifted wheel keeps B finite) */
#define RH_MF_FZ_CAP_FACTOR 2.0  /* loads are capped at this times Fz0, - */

/* One pure-slip curve as configured (Python MfCurve; mf_tyre_fit.toml), doubles. */
typedef struct {
  double fz0_n; /* normalising load Fz0, N */
  double c;     /* shape factor C, - */
  double d1;    /* peak friction coefficient, - */
  double d2;    /* its load sensitivity, - */
  double k1;    /* slip-stiffness coefficient, (N/rad)/N */
  double k2;    /* its load sensitivity, (N/rad)/N */
  double k3;    /* exponential load sensitivity, - */
  double e1;    /* curvature, - */
  double e2;    /* its load sensitivity, - */
} rh_mf_curve_config_t;

/* The same curve in working precision (same units as the config). */
typedef struct {
  real_t fz0_n, c, d1, d2, k1, k2, k3, e1, e2;
} rh_mf_curve_t;

void rh_mf_curve_init(rh_mf_curve_t *cv, const rh_mf_curve_config_t *cfg);

/* Largest load the formulas are evaluated at, N: RH_MF_FZ_CAP_FACTOR * Fz0 (double). */
double rh_mf_fz_cap(const rh_mf_curve_config_t *cfg);

/* F(s), N, at slip s (alpha rad), load fz_n N (>= RH_MF_FZ_MIN_N), friction scaling mu (-). */
real_t rh_mf_force(const rh_mf_curve_t *cv, real_t s, real_t fz_n, real_t mu);

/* out = (F N, dF/ds N/rad, dF/dFz N/N) at the same arguments. */
void rh_mf_eval(const rh_mf_curve_t *cv, real_t s, real_t fz_n, real_t mu, real_t out[3]);

#endif /* RH_MF_TYRE_H */
