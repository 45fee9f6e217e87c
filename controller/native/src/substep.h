/* Guarded Heun sub-stepping with forward-mode sensitivities, shared by the 3-state physics
 * prediction models (Python reference: controller/core/model/_substep.py).
 *
 * A model supplies the continuous right-hand side g(x) for x = [vx m/s, vy m/s, r rad/s]
 * (and its Jacobian): g[0..2] = (dvx/dt m/s^2, dvy/dt m/s^2, dr/dt rad/s^2); with
 * Jacobian g[3..11] = dg/dx row-major, g[12..14] = dg/dDeltaM (per N m). The per-call
 * constants (steering, torques) live in a caller-owned struct passed as `call`.
 *
 * One model step of ts seconds is n Heun sub-steps of h = ts/n,
 * n = max(ceil(ts/h_max), ceil(ts*lambda/H_LAMBDA_MAX)), lambda = stiff_rate/max(|vx|, V_LOW),
 * clamped to [1, RH_SUBSTEP_MAX]. Sensitivities S = dz/dx0, sb = dz/dDeltaM go through the
 * same sub-steps (exact chain rule), so A, B are the exact derivative of the discrete map.
 *
 * Guard: non-finite x, DeltaM, delta_w, Tt or ts, ts outside (0, 1] s, or a non-finite result
 * fills every output with NaN (the caller treats NaN as a failed step). */
#ifndef RH_SUBSTEP_H
#define RH_SUBSTEP_H

#include "rh_params.h"
#include "rh_real.h"

#define RH_SUBSTEP_MAX_TS_S 1.0   /* longest accepted step, s */
#define RH_SUBSTEP_MAX 200        /* upper bound on sub-steps per call */
#define RH_SUBSTEP_V_LOW_MPS 1.0  /* slip-denominator floor, m/s */
#define RH_SUBSTEP_H_LAMBDA_MAX 0.5 /* largest h*lambda per Heun sub-step, - */

/* g (3) = continuous derivative at (vx m/s, vy m/s, r rad/s). */
typedef void (*rh_substep_rhs_fn)(const void *call, real_t vx, real_t vy, real_t r,
                                  real_t g[3]);
/* g (15) = derivative (3), its Jacobian dg/dx row-major (9), dg/dDeltaM per N m (3). */
typedef void (*rh_substep_rhs_jac_fn)(const void *call, real_t vx, real_t vy, real_t r,
                                      real_t g[15]);

/* Upper bound of |lambda|*vx of the linear lateral dynamics, m/s^2, from the axle
 * cornering stiffnesses cf, cr (N/rad, either sign), mass (kg), Iz (kg m^2), lf, lr (m). */
double rh_substep_stiffness_rate(double cf_n_per_rad, double cr_n_per_rad, double mass_kg,
                                 double yaw_inertia_kgm2, double lf_m, double lr_m);

/* Validate the inputs; return the number of sub-steps (0 = invalid input).
 * h_max_s: sub-step bound, s. stiff_rate: m/s^2 (rh_substep_stiffness_rate). */
int rh_substep_count(const real_t x[3], real_t delta_m, const rh_ctx_t *ctx, double h_max_s,
                     double stiff_rate);

/* xn = n Heun sub-steps of length ts/n from x (NaN-filled if not finite). */
void rh_substep_predict(rh_substep_rhs_fn rhs, const void *call, int n, real_t ts,
                        const real_t x[3], real_t xn[3]);

/* xn (may be NULL), A (3x3 row-major dxn/dx) and B (3, dxn/dDeltaM per N m) by n Heun
 * sub-steps with sensitivities (NaN-filled if not finite). */
void rh_substep_propagate(rh_substep_rhs_jac_fn rhs_jac, const void *call, int n, real_t ts,
                          const real_t x[3], real_t xn[3], real_t A[9], real_t B[3]);

/* The failure output: xn (if not NULL), A, B filled with NaN. */
void rh_substep_fail(real_t xn[3], real_t A[9], real_t B[3]);

/* x (3) = [vx m/s, vy m/s, r rad/s] from the bus inputs (PredictionModel.initial_state). */
void rh_substep_initial_state(real_t vx, real_t vy, real_t yaw_rate, real_t x[3]);

#endif /* RH_SUBSTEP_H */
