/* Passive baseline controller step: dM = 0, the driver's torque (pedal map) split by the
 * allocator within the motor limits (paper IV-B). Python reference:
 * controller/core/passive.py (PassiveController.step; allocate_only is the same call).
 * Nothing is learned: the only state is the allocator's (tt_applied, dm_applied). */
#ifndef RH_PASSIVE_H
#define RH_PASSIVE_H

#include "allocation.h"
#include "rh_real.h"

#define RH_QP_NOT_RUN 4 /* QpStatus.NOT_RUN (controller/core/interfaces.py) */

/* The fields of ControllerOutputs the passive step sets. */
typedef struct {
  real_t torques[4];  /* wheel torque commands FL, FR, RL, RR, N m */
  real_t total_torque;/* driver's demand Tt from the pedal map, N m */
  real_t delta_m;     /* realised dM (allocator dm_applied), N m */
  int qp_status;      /* RH_QP_NOT_RUN */
  int qp_iterations;  /* 0 */
  int fallback;       /* 0 */
} rh_passive_out_t;

/* PassiveController.reset: torques, Tt, dM to 0; status NOT_RUN. */
void rh_passive_reset(rh_passive_out_t *out);

/* One step: Tt = pedal map (accel, brake 0..1, T_peak of the allocator), dM = 0,
 * out->torques = allocation at ax, ay m/s^2 (non-finite read as 0) and wheel speeds ws (4,)
 * rad/s (NULL reads as zeros, like an unreadable Python sequence). */
void rh_passive_step(rh_alloc_t *alloc, real_t accel, real_t brake, real_t ax, real_t ay,
                     const real_t ws[4], rh_passive_out_t *out);

/* sizeof(rh_passive_out_t), bytes (layout checks of bindings). */
int rh_passive_out_size(void);

#endif /* RH_PASSIVE_H */
