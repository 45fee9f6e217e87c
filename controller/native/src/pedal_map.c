/* Pedal map (see pedal_map.h). */
#include "pedal_map.h"

real_t rh_pedal_clip(real_t v) {
  if (!RH_FINITE(v)) return RH_R(0.0);
  return v < RH_R(0.0) ? RH_R(0.0) : (v > RH_R(1.0) ? RH_R(1.0) : v);
}

real_t rh_pedal_total_torque(real_t accel, real_t brake, real_t peak_torque_nm) {
  return (rh_pedal_clip(accel) - rh_pedal_clip(brake)) * RH_R(4.0) * peak_torque_nm;
}
