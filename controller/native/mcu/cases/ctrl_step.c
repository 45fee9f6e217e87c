/* Case adapter of the full controller step (include/rhonn_core.h): rh_ctrl_init from the
 * generated config initialiser, then rh_ctrl_step per recorded input vector.
 *
 * mcu_case_config.h (generated, harness/bench/mcu/case.py ctrl_step_case) must define
 *   static const rh_ctrl_config_t MCU_CONFIG = {...};
 *   MCU_CTRL_N_IN, MCU_CTRL_N_OUT: the lengths of the flat vectors of rh_inputs_t and
 *     rh_outputs_t (ints carried as float values);
 *   static void mcu_inputs_from(const float v[], rh_inputs_t *s);
 *   static void mcu_outputs_to(const rh_outputs_t *s, float v[]);
 * the vectors and both functions laid out from rhonn_core.h's structs by
 * harness/bench/mcu/layout.py (every field in the header's order).
 * Built with the core's C99 flags and -DRH_FLOAT32. */
#include "mcu_case.h"
#include "rhonn_core.h"
#include "mcu_case_config.h"

typedef char mcu_real_is_float[sizeof(real_t) == sizeof(float) ? 1 : -1];
typedef char mcu_dims_match[(MCU_N_IN == MCU_CTRL_N_IN && MCU_N_OUT == MCU_CTRL_N_OUT) ? 1 : -1];

static rh_ctrl_t ctrl; /* the controller's whole state (harness-owned storage) */

void mcu_case_init(void) {
  int rc = rh_ctrl_init(&ctrl, &MCU_CONFIG);
  if (rc != 0) mcu_case_fail(rc < 0 ? -rc : rc);
}

void mcu_case_step(const float in[MCU_N_IN], float out[MCU_N_OUT]) {
  rh_inputs_t x;
  rh_outputs_t y;
  mcu_inputs_from(in, &x);
  rh_ctrl_step(&ctrl, &x, &y);
  mcu_outputs_to(&y, out);
}
