/* Pedal map: driver pedals -> total wheel-torque demand Tt (contract shared with the plant).
 *   Tt = (accel - brake) 4 T_peak   N m, pedals in 0..1 (clipped; non-finite reads as 0).
 * Python reference: controller/core/pedal_map.py (total_torque_from_pedals). */
#ifndef RH_PEDAL_MAP_H
#define RH_PEDAL_MAP_H

#include "rh_real.h"

/* A pedal position clipped to 0..1; non-finite reads as released (0), -. */
real_t rh_pedal_clip(real_t v);

/* Tt, N m, for pedal positions accel, brake (0..1, -) and the per-motor peak torque, N m. */
real_t rh_pedal_total_torque(real_t accel, real_t brake, real_t peak_torque_nm);

#endif /* RH_PEDAL_MAP_H */
