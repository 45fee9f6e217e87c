/* Linear 2-DoF bicycle ("single-track") model: the LMPC's prediction model (paper IV-B).
 * Python reference: controller/core/model/bicycle.py (BicycleModel), sub-stepping substep.h.
 *
 * States x = [vx m/s, vy m/s, r rad/s]; input DeltaM N m; ctx->delta_w (rad) and
 * ctx->total_torque Tt (N m) held over the step of ctx->ts seconds.
 *
 *   dvx/dt = Tt / (m R)
 *   dvy/dt = (Fyf + Fyr) / m - vx r
 *   dr/dt  = (lf Fyf - lr Fyr) / Iz + wB / (2 R Iz) DeltaM
 *   Fyf = Cf af, af = (vy + lf r)/vx - delta;  Fyr = Cr ar, ar = (vy - lr r)/vx
 * Cf, Cr: the paper's NEGATIVE axle cornering stiffnesses (N/rad). Below V_LOW = 1 m/s the
 * slip denominator is V_LOW and the steering term fades as delta |vx| / V_LOW. */
#ifndef RH_BICYCLE_H
#define RH_BICYCLE_H

#include <stddef.h>

#include "rh_params.h"
#include "rh_real.h"

typedef struct {
  double h_max_s;    /* sub-step bound, s (reference default 0.05) */
  double stiff_rate; /* bound of |lambda| vx of the lateral dynamics, m/s^2 */
  real_t m;          /* mass, kg */
  real_t iz;         /* yaw inertia, kg m^2 */
  real_t lf;         /* CG to front axle, m */
  real_t lr;         /* CG to rear axle, m */
  real_t cf;         /* front axle cornering stiffness, N/rad (negative) */
  real_t cr;         /* rear axle cornering stiffness, N/rad (negative) */
  real_t kdm;        /* wB / (2 R Iz): yaw acceleration per DeltaM, 1/(kg m^2) */
  real_t radius;     /* wheel radius R, m */
} rh_bicycle_t;

/* Constants from the vehicle p; h_max_s: sub-step bound, s (0.05 as make_model). The step
 * length is NOT a constant: it is ctx->ts per call, as in the reference. */
void rh_bicycle_init(rh_bicycle_t *m, const rh_vehicle_t *p, double h_max_s);

/* xn (3) = state after ctx->ts seconds with DeltaM dm (N m) held; NaN on invalid input. */
void rh_bicycle_predict(const rh_bicycle_t *m, const real_t x[3], real_t dm,
                        const rh_ctx_t *ctx, real_t xn[3]);

/* predict + Jacobians in one pass: xn (3), A (3x3 row-major dxn/dx), B (3, dxn/dDeltaM per
 * N m). The xn of this path equals rh_bicycle_predict's up to rounding (the reference's two
 * paths evaluate the right-hand side in slightly different orders). NaN on invalid input. */
void rh_bicycle_predict_linearize(const rh_bicycle_t *m, const real_t x[3], real_t dm,
                                  const rh_ctx_t *ctx, real_t xn[3], real_t A[9],
                                  real_t B[3]);

/* sizeof(rh_bicycle_t), bytes (layout checks of bindings). */
size_t rh_bicycle_sizeof(void);

#endif /* RH_BICYCLE_H */
