/* Passive baseline step (see passive.h). */
#include "passive.h"

#include "pedal_map.h"

void rh_passive_reset(rh_passive_out_t *out) {
  int i;
  for (i = 0; i < 4; i++) out->torques[i] = RH_R(0.0);
  out->total_torque = RH_R(0.0);
  out->delta_m = RH_R(0.0);
  out->qp_status = RH_QP_NOT_RUN;
  out->qp_iterations = 0;
  out->fallback = 0;
}

void rh_passive_step(rh_alloc_t *alloc, real_t accel, real_t brake, real_t ax, real_t ay,
                     const real_t ws[4], rh_passive_out_t *out) {
  static const real_t zeros[4] = {0, 0, 0, 0};
  real_t tt = rh_pedal_total_torque(accel, brake, alloc->peak_torque);
  rh_alloc_allocate(alloc, tt, RH_R(0.0), RH_FINITE(ax) ? ax : RH_R(0.0),
                    RH_FINITE(ay) ? ay : RH_R(0.0), ws ? ws : zeros, 0, out->torques);
  out->total_torque = tt;
  out->delta_m = alloc->dm_applied;
  out->qp_status = RH_QP_NOT_RUN;
  out->qp_iterations = 0;
  out->fallback = 0;
}

int rh_passive_out_size(void) { return (int)sizeof(rh_passive_out_t); }
