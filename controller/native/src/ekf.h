/* Guarded EKF weight learning of the RHONN, standard form (paper eq. 10-12).
 * Python reference: controller/core/learning/ekf.py (BatchedEkf).
 *
 * RH_EKF_N = 3 independent scalar-measurement filters (one per neuron / state
 * [Vx m/s, Vy m/s, wr rad/s]) of RH_NPHI = 15 weights, sharing the regressor H = phi:
 *   s_i = R_i + H' P_i H;  K_i = P_i H / s_i;  W_i += zeta_i K_i e_i   (e = x - chi)
 *   P_i -= u u' (u = P_i H / sqrt(s_i), exactly symmetric);  P_i += q I
 * Guards (counted in rh_ekf_counters_t): non-finite sum(h) / sum(e) or non-finite /
 * non-positive s -> rejected, nothing changes; diag(P_i) >= p_floor; trace(P_i) >
 * trace_max -> P_i = p0 I; |W| <= w_max; every eig_check_every accepted updates the
 * eigenvalues of every P_i are floored at p_floor (cyclic Jacobi, rh_ekf_enforce_spd).
 *
 * Units: state unit u (m/s for Vx, Vy; rad/s for wr). W in u (phi is dimensionless),
 * P, q, R in u^2. Layout: W (3, 15) row-major, P (3, 15, 15) row-major. */
#ifndef RH_EKF_H
#define RH_EKF_H

#include "ekf_counters.h"
#include "rh_real.h"
#include "rhonn.h"

#define RH_EKF_N 3                                /* filters (neurons) */
#define RH_EKF_L RH_NPHI                          /* weights per filter */
#define RH_EKF_NP (RH_EKF_N * RH_EKF_L * RH_EKF_L) /* entries of P */
#define RH_EKF_JACOBI_SWEEPS 50                   /* max cyclic Jacobi sweeps */
#define RH_EKF_EIG_MAX (RH_NPHI + 1) /* largest P rh_ekf_floor_spd takes (yaw_gain.h's 16) */

/* Tuning (Python: EkfConfig; form is chosen by the type: rh_ekf_t or rh_ud_ekf_t). */
typedef struct {
  double p0;              /* initial covariance P0 = p0 I, u^2 */
  double q;               /* weight random-walk covariance per update, u^2 */
  double r[RH_EKF_N];     /* measurement noise covariance per neuron, u^2 */
  double zeta[RH_EKF_N];  /* learning rate per neuron, - */
  double p_floor;         /* diagonal / eigenvalue floor of P, u^2 */
  double trace_max;       /* trace bound of each P_i, u^2 */
  double w_max;           /* |W| bound, u */
  int eig_check_every;    /* accepted updates between eigenvalue floors (0 = never), - */
} rh_ekf_config_t;

/* The tuning of either form in the working precision (rounded once from the config). */
typedef struct {
  real_t R[RH_EKF_N];     /* cfg.r, u^2 */
  real_t zeta[RH_EKF_N];  /* cfg.zeta, - */
  real_t q;               /* u^2 */
  real_t p_floor;         /* diagonal / eigenvalue floor (UD: floor of D), u^2 */
  real_t trace_max;       /* u^2 */
  real_t p0;              /* u^2 */
  real_t w_max;           /* u */
} rh_ekf_tuning_t;

/* Tuning from the config, and w0 (NULL: zeros) into W0 (both forms' init). */
void rh_ekf_tuning_init(rh_ekf_tuning_t *t, const rh_ekf_config_t *cfg,
                        const real_t w0[RH_NW], real_t W0[RH_NW]);

typedef struct {
  real_t W[RH_NW];        /* weights (3, 15), u */
  real_t P[RH_EKF_NP];    /* covariances (3, 15, 15), u^2 */
  real_t w0[RH_NW];       /* initial weights (3, 15), u */
  rh_ekf_tuning_t t;
  rh_ekf_counters_t counters;
  rh_ekf_config_t cfg;    /* the configuration as given (double) */
  int since_eig;          /* accepted updates since the last eigenvalue floor, - */
} rh_ekf_t;

/* Copy cfg, set w0 (NULL: zeros) and reset (cold start). */
void rh_ekf_init(rh_ekf_t *f, const rh_ekf_config_t *cfg, const real_t w0[RH_NW]);

/* Cold start: W = w0, P_i = p0 I, counters and since_eig zeroed. */
void rh_ekf_reset(rh_ekf_t *f);

/* One learning step with regressor h (15,) and errors e (3,) = x - chi.
 * Returns 1 when the weights were updated, 0 when rejected (state unchanged). */
int rh_ekf_update(rh_ekf_t *f, const real_t h[RH_EKF_L], const real_t e[RH_EKF_N]);

/* e_out = x - chi (3,), then rh_ekf_update(f, h, e_out) (RhonnModel.observe). */
int rh_ekf_update_error(rh_ekf_t *f, const real_t h[RH_EKF_L], const real_t x[RH_EKF_N],
                        const real_t chi[RH_EKF_N], real_t e_out[RH_EKF_N]);

/* Learning frozen this step (update(..., learn=False)): counts it, changes nothing. */
void rh_ekf_freeze(rh_ekf_t *f);

/* Floor the eigenvalues of every P_i at p_floor (cyclic Jacobi, at most
 * RH_EKF_JACOBI_SWEEPS sweeps); a P_i with a non-finite entry or eigenvalue is reset to
 * p0 I. A P_i whose eigenvalues are all >= p_floor is left bit-for-bit unchanged.
 * Returns the number of P_i repaired (also added to counters.eig_repairs). */
int rh_ekf_enforce_spd(rh_ekf_t *f);

/* Floor the eigenvalues of one symmetric n x n covariance P (row-major, 1 <= n <=
 * RH_EKF_EIG_MAX) at p_floor, in place, as rh_ekf_enforce_spd does for each P_i: unchanged
 * bit for bit when every eigenvalue is >= p_floor, p0 I when an entry or eigenvalue is not
 * finite. Returns 1 when P was repaired, else 0 (also for an n out of range). */
int rh_ekf_floor_spd(real_t *P, int n, real_t p_floor, real_t p0);

/* Eigen-decomposition of a symmetric 15x15 matrix A (row-major, not modified) by cyclic
 * Jacobi: A = V diag(lam) V' with the eigenvectors in the columns of V (row-major),
 * lam unsorted. Returns the sweeps used (> RH_EKF_JACOBI_SWEEPS: not converged). */
int rh_ekf_jacobi_eig(const real_t A[RH_EKF_L * RH_EKF_L], real_t V[RH_EKF_L * RH_EKF_L],
                      real_t lam[RH_EKF_L]);

/* sizeof(rh_ekf_t), sizeof(rh_ekf_config_t), sizeof(rh_ekf_counters_t), bytes
 * (layout checks of bindings). */
void rh_ekf_sizes(int out[3]);

#endif /* RH_EKF_H */
