/* UD-factored form of the RHONN weight EKF (Bierman measurement update, rank-one
 * Agee-Turner time update P <- P + q I). Python reference:
 * controller/core/learning/ud_ekf.py (UdEkf). Same filter, configuration (rh_ekf_config_t) and counters as
 * ekf.h; the form required for float32 builds (P = U D U' stays positive definite).
 *
 * Per neuron i: U_i (15, 15) unit upper triangular, of which only the strictly upper part
 * is stored, packed by columns (entry (a, j), a < j, at RH_UD_AT(a, j)): 105 entries
 * instead of 225; D_i (15,) > 0. Guards: non-finite sum(h) / sum(e) or non-finite / non-positive
 * innovation variance -> rejected (state unchanged); D_j >= p_floor; trace(P_i) >
 * trace_max -> U_i = I, D_i = p0 (counted); |W| <= w_max (counted). No eigenvalue floor
 * (cfg.eig_check_every is ignored; counters.eig_repairs stays 0).
 * Units: W in u, D in u^2, U dimensionless (u: m/s for Vx, Vy; rad/s for wr). */
#ifndef RH_UD_EKF_H
#define RH_UD_EKF_H

#include "ekf.h"

#define RH_UD_NU (RH_EKF_L * (RH_EKF_L - 1) / 2) /* stored entries of one U_i */
#define RH_UD_AT(a, j) ((((j) * ((j) - 1)) / 2) + (a)) /* packed index of U_i(a, j), a < j */

typedef struct {
  real_t W[RH_NW];        /* weights (3, 15), u */
  real_t U[RH_EKF_N * RH_UD_NU]; /* strictly upper parts of U_i, packed (3, 105), - */
  real_t D[RH_NW];        /* diagonal factors (3, 15), u^2 */
  real_t w0[RH_NW];       /* initial weights (3, 15), u */
  rh_ekf_tuning_t t;
  rh_ekf_counters_t counters;
  rh_ekf_config_t cfg;    /* the configuration as given (double) */
} rh_ud_ekf_t;

/* Copy cfg, set w0 (NULL: zeros) and reset (cold start). */
void rh_ud_ekf_init(rh_ud_ekf_t *f, const rh_ekf_config_t *cfg, const real_t w0[RH_NW]);

/* Cold start: W = w0, U_i = I, D_i = p0, counters zeroed. */
void rh_ud_ekf_reset(rh_ud_ekf_t *f);

/* P <- P + q I on a UD factor (U: n x n unit upper triangular; packed = 1: its strictly
 * upper part packed by columns as RH_UD_AT, 0: the whole matrix row-major; D: n; q >= 0)
 * as n rank-one updates (Agee-Turner); fv: n scratch entries. Shared by the EKF's
 * neurons (packed) and the ΔM-gain filter (yaw_gain.c, row-major). */
void rh_ud_add_scaled_identity(real_t *U, real_t *D, int n, int packed, real_t q, real_t *fv);

/* One learning step with regressor h (15,) and errors e (3,) = x - chi.
 * Returns 1 when the weights were updated, 0 when rejected (state unchanged). */
int rh_ud_ekf_update(rh_ud_ekf_t *f, const real_t h[RH_EKF_L], const real_t e[RH_EKF_N]);

/* e_out = x - chi (3,), then rh_ud_ekf_update(f, h, e_out) (RhonnModel.observe). */
int rh_ud_ekf_update_error(rh_ud_ekf_t *f, const real_t h[RH_EKF_L],
                           const real_t x[RH_EKF_N], const real_t chi[RH_EKF_N],
                           real_t e_out[RH_EKF_N]);

/* Learning frozen this step: counts it, changes nothing. */
void rh_ud_ekf_freeze(rh_ud_ekf_t *f);

/* P_i = U_i diag(D_i) U_i' (3, 15, 15) row-major, u^2 (UdEkf.P / get_state). Accumulated
 * in double in both precisions (the Python property works in float64). */
void rh_ud_ekf_covariance(const rh_ud_ekf_t *f, double P[RH_EKF_NP]);

/* Factorise P (3, 15, 15) row-major, u^2, symmetric positive definite, into U, D
 * (UdEkf.set_state / udu_factor; accumulated in double). W is not touched.
 * Returns the number of non-finite or non-positive D_j produced (0: fine); the factors
 * are stored regardless, like the reference. */
int rh_ud_ekf_set_covariance(rh_ud_ekf_t *f, const double P[RH_EKF_NP]);

/* sizeof(rh_ud_ekf_t), bytes (layout checks of bindings). */
int rh_ud_ekf_size(void);

#endif /* RH_UD_EKF_H */
