/* Case adapter of the full controller step (include/rhonn_core.h): rh_ctrl_init from the
 * generated config initialiser, then rh_ctrl_step per recorded input vector.
 *
 * mcu_case_config.h (generated, harness/bench/mcu/case.py ctrl_step_case) must define
 *   static const rh_ctrl_config_t MCU_CONFIG = {...};
 * Flat layouts (harness/bench/mcu/case.py CTRL_INPUTS / CTRL_OUTPUTS; ints carried as float):
 *   in : swa_rad accel_pedal brake_pedal yaw_rate ax ay ws0 ws1 ws2 ws3 vx vy
 *        stab_enable sensors_valid wheel_speeds_usable                          (15)
 *   out: torque0..3 total_torque delta_m yaw_rate_ref vy_ref beta_ref qp_status
 *        qp_iterations fallback pred_vx pred_vy pred_r                           (15)
 * Built with the core's C99 flags and -DRH_FLOAT32. */
#include "mcu_case.h"
#include "rhonn_core.h"
#include "mcu_case_config.h"

typedef char mcu_real_is_float[sizeof(real_t) == sizeof(float) ? 1 : -1];
typedef char mcu_dims_match[(MCU_N_IN == 15 && MCU_N_OUT == 15) ? 1 : -1];

static rh_ctrl_t ctrl; /* the controller's whole state (harness-owned storage) */

void mcu_case_init(void) {
  int rc = rh_ctrl_init(&ctrl, &MCU_CONFIG);
  if (rc != 0) mcu_case_fail(rc < 0 ? -rc : rc);
}

void mcu_case_step(const float in[MCU_N_IN], float out[MCU_N_OUT]) {
  rh_inputs_t x;
  rh_outputs_t y;
  int j;
  x.swa_rad = in[0];
  x.accel_pedal = in[1];
  x.brake_pedal = in[2];
  x.yaw_rate = in[3];
  x.ax = in[4];
  x.ay = in[5];
  for (j = 0; j < 4; j++) x.wheel_speeds[j] = in[6 + j];
  x.vx = in[10];
  x.vy = in[11];
  x.stab_enable = (int)in[12];
  x.sensors_valid = (int)in[13];
  x.wheel_speeds_usable = (int)in[14];
  rh_ctrl_step(&ctrl, &x, &y);
  for (j = 0; j < 4; j++) out[j] = y.torques[j];
  out[4] = y.total_torque;
  out[5] = y.delta_m;
  out[6] = y.yaw_rate_ref;
  out[7] = y.vy_ref;
  out[8] = y.beta_ref;
  out[9] = (float)y.qp_status;
  out[10] = (float)y.qp_iterations;
  out[11] = (float)y.fallback;
  for (j = 0; j < 3; j++) out[12 + j] = y.model_prediction[j];
}
