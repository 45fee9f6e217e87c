/* The yaw-moment effectiveness theta, learned jointly with the RHONN's yaw-rate weights.
 * Python reference: controller/core/learning/input_gain.py (YawGainFilter).
 *
 * The yaw row's increment is dwr = w_r' phi + theta u, u = the known Delta M part at
 * theta = 1 (rad/s). The 16 unknowns x = [w_r (15), theta] are one scalar-measurement
 * Kalman filter with the regressor h = [phi, u] and the yaw row's error e_r = wr - chi_r,
 * in the form of the state weights' EKF and with its tuning (the yaw row's R and zeta):
 *   standard (as ekf.c): s = R + h' P h; x += zeta (P h / s) e_r; P -= v v' (v = P h /
 *     sqrt(s)); P += q I; diag(P) >= p_floor; trace(P) > trace_max -> P = p0 I (theta's
 *     variance too, like the reference); every eig_check_every accepted updates the
 *     eigenvalues are floored (rh_ekf_floor_spd);
 *   UD (as ud_ekf.c): Bierman measurement update, Agee-Turner time update (P + q I),
 *     D >= p_floor, trace(P) > trace_max -> U = I, D = p0.
 * Then |W| <= w_max (counted) and theta clipped to [dm_gain_min, dm_gain_max] (uncounted).
 * Rejected (nothing changes) on non-finite sum(h) / e_r or non-finite / non-positive s.
 * A cold start is x = [w_r0, 1], P = p0 I with theta's variance dm_gain_p0.
 *
 * Units: w_r and e_r in rad/s, theta -, u rad/s; P (standard) and D (UD) entry (a, b) in the
 * product of the units of x_a and x_b ((rad/s)^2, rad/s, -^2); U dimensionless. */
#ifndef RH_YAW_GAIN_H
#define RH_YAW_GAIN_H

#include "ekf.h"
#include "ekf_counters.h"
#include "rh_real.h"
#include "rhonn.h"

#define RH_YAW_GAIN_L (RH_NPHI + 1)                  /* unknowns: w_r and theta */
#define RH_YAW_GAIN_LL (RH_YAW_GAIN_L * RH_YAW_GAIN_L) /* entries of P or U */
#define RH_YAW_GAIN_THETA RH_NPHI                     /* index of theta in x */

/* [rhonn] dm_gain_* (Python: RhonnConfig; same names, so controller/native/config.py fills
 * it field by field). */
typedef struct {
  double dm_gain_p0;  /* prior variance of theta, -^2 (0: off, theta = 1) */
  double dm_gain_min; /* lower bound of theta, - (0 < min <= 1) */
  double dm_gain_max; /* upper bound of theta, - (>= 1) */
} rh_yaw_gain_config_t;

typedef struct {
  real_t W[RH_YAW_GAIN_L];  /* estimate x = [w_r (rad/s), theta (-)] */
  real_t PU[RH_YAW_GAIN_LL]; /* (16, 16) row-major: the covariance P (standard form), or
                             * the unit upper triangular factor U (UD form), - */
  real_t D[RH_YAW_GAIN_L];  /* UD form: diagonal factor (unused in the standard form) */
  real_t w0[RH_YAW_GAIN_L]; /* cold-start estimate [w_r0, 1] */
  real_t r;                 /* the yaw row's measurement noise covariance, (rad/s)^2 */
  real_t zeta;              /* the yaw row's learning rate, - */
  real_t q;                 /* the state weights' tuning (ekf.h): random walk, u^2 */
  real_t p_floor;           /* ... floor of diag(P) (UD: of D), u^2 */
  real_t trace_max;         /* ... trace bound, u^2 */
  real_t p0;                /* ... initial (and trace-reset) variance, u^2 */
  real_t w_max;             /* ... |W| bound, u */
  real_t theta_p0;          /* prior variance of theta, -^2 */
  real_t theta_min;         /* lower bound of theta, - */
  real_t theta_max;         /* upper bound of theta, - */
  int ud;                   /* 1: UD form, 0: standard form */
  int eig_check_every;      /* standard form: accepted updates between eigenvalue floors */
  int since_eig;            /* accepted updates since the last eigenvalue floor */
  rh_ekf_counters_t counters;
} rh_yaw_gain_t;

/* Set up from the config, the state weights' tuning (its yaw row, index 2) and the form
 * (ud: 1 UD, 0 standard), with w_r0 (15) the yaw row's initial weights, rad/s; then a cold
 * start. Returns 0, or -1 (g zeroed) when dm_gain_p0 is not a positive number or the bounds
 * are not 0 < dm_gain_min <= 1 <= dm_gain_max. */
int rh_yaw_gain_init(rh_yaw_gain_t *g, const rh_yaw_gain_config_t *cfg,
                     const rh_ekf_config_t *ekf, int ud, const real_t w_r0[RH_NPHI]);

/* Cold start: W = [w_r0, 1], P = p0 I with theta's variance theta_p0, counters zeroed. */
void rh_yaw_gain_reset(rh_yaw_gain_t *g);

/* One update with the regressor phi (15), the known Delta M part u (rad/s, at theta = 1) and
 * the yaw-rate error e_r (rad/s). Returns 1 when the estimate changed, 0 when rejected. */
int rh_yaw_gain_update(rh_yaw_gain_t *g, const real_t phi[RH_NPHI], real_t u, real_t e_r);

/* sizeof(rh_yaw_gain_t), bytes. */
int rh_yaw_gain_size(void);

#endif /* RH_YAW_GAIN_H */
