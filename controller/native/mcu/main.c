/* MCU test main: runs the recorded input vectors through the case's step and prints, per
 * step, the outputs as float32 bit patterns (exact round trip) and the step's stack use.
 *
 * Output protocol (semihosting, one line each):
 *   MCU begin <n_steps> <n_in> <n_out> <n_baseline>
 *   DWT <ctrl> <cyccnt delta over a 100-iteration loop>   (0 0: no cycle counter modelled)
 *   O <k> <stack bytes> <out_0 bits> ... <out_{n_out-1} bits>
 *   MCU end
 * Instruction counts: mcu_mark() is called <n_baseline> times in pairs with nothing between
 * (the baseline), then right before and right after every step; the QEMU plugin
 * (qemu_insn_plugin.c) logs the guest instruction count at each entry of mcu_mark.
 * Harness code: GNU C. */
#include <stdint.h>
#include <string.h>

#include "mcu_case.h"
#include "mcu_case_inputs.h"
#include "semihost.h"
#include "stack_watch.h"

#define N_BASELINE 4


void mcu_case_fail(int code) {
  ln_str("FAIL ");
  ln_dec((uint32_t)code);
  ln_str("\n");
  ln_flush();
  sh_exit(1);
}

__attribute__((noinline)) void mcu_mark(void) { __asm__ volatile("" ::: "memory"); }


#define DEMCR (*(volatile uint32_t *)0xE000EDFCu)
#define DWT_CTRL (*(volatile uint32_t *)0xE0001000u)
#define DWT_CYCCNT (*(volatile uint32_t *)0xE0001004u)

static void probe_dwt(void) {
  uint32_t c0, c1, ctrl;
  volatile uint32_t sink = 0;
  int i;
  DEMCR |= (1u << 24); /* TRCENA */
  DWT_CYCCNT = 0u;
  DWT_CTRL |= 1u; /* CYCCNTENA */
  ctrl = DWT_CTRL;
  c0 = DWT_CYCCNT;
  for (i = 0; i < 100; i++) sink += (uint32_t)i;
  c1 = DWT_CYCCNT;
  ln_str("DWT ");
  ln_hex32(ctrl);
  ln_str(" ");
  ln_dec(c1 - c0);
  ln_str("\n");
  ln_flush();
}

int main(void) {
  static float in[MCU_N_IN], out[MCU_N_OUT];
  uint32_t k, i, sp, used;

  ln_str("MCU begin ");
  ln_dec(MCU_N_STEPS); ln_str(" ");
  ln_dec(MCU_N_IN); ln_str(" ");
  ln_dec(MCU_N_OUT); ln_str(" ");
  ln_dec(N_BASELINE); ln_str("\n");
  ln_flush();
#ifndef MCU_NO_DWT_PROBE
  probe_dwt();
#endif
  mcu_case_init();
  for (i = 0; i < N_BASELINE; i++) {
    mcu_mark();
    mcu_mark();
  }
  for (k = 0; k < MCU_N_STEPS; k++) {
    memcpy(in, MCU_INPUT_BITS[k], sizeof in);
    stack_paint();
    sp = sp_now();
    mcu_mark();
    mcu_case_step(in, out);
    mcu_mark();
    used = sp - stack_low_water();
    ln_str("O ");
    ln_dec(k); ln_str(" ");
    ln_dec(used);
    for (i = 0; i < MCU_N_OUT; i++) {
      uint32_t bits;
      memcpy(&bits, &out[i], sizeof bits);
      ln_str(" ");
      ln_hex32(bits);
    }
    ln_str("\n");
    ln_flush();
  }
  ln_str("MCU end\n");
  ln_flush();
  return 0;
}
