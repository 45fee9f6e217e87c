/* CMAC case of the MCU harness: per step, the AES-128-CMAC (node_cmac.c) of one SecOC MAC
 * input (ID 2 bytes || payload 8 || FV 8: 18 bytes, two AES blocks) under a fixed key.
 * The step's input is the message's index into MCU_CMAC_MESSAGES, its 16 outputs the tag's
 * bytes (0..255); key and messages generated in Python (harness/bench/mcu/cmac_case.py).
 * Built with the core's C99 flags and -DRH_FLOAT32. */
#include <stdint.h>

#include "mcu_case.h"
#include "mcu_case_config.h"
#include "node_cmac.h"

typedef char mcu_dims_match[(MCU_N_IN == 1 && MCU_N_OUT == RH_NODE_CMAC_BLOCK) ? 1 : -1];

static rh_node_cmac_key_t key;

void mcu_case_init(void) { rh_node_cmac_init(&key, MCU_CMAC_KEY); }

void mcu_case_step(const float in[MCU_N_IN], float out[MCU_N_OUT]) {
  uint8_t tag[RH_NODE_CMAC_BLOCK];
  unsigned k = (unsigned)in[0];
  unsigned i;
  if (k >= MCU_N_STEPS) mcu_case_fail(2);
  rh_node_cmac_compute(&key, MCU_CMAC_MESSAGES[k], MCU_CMAC_MESSAGE_BYTES, tag);
  for (i = 0; i < RH_NODE_CMAC_BLOCK; i++) out[i] = (float)tag[i];
}
