/* Stack high-water measurement of the firmware (GNU C: the stack pointer is read with asm).
 * The linker script (mps2_an386.ld) provides __stack_limit, the lowest stack address. Paint
 * the free stack once before the code to be measured, then read the lowest word that code
 * overwrote. Header-only: each firmware main includes it once. */
#ifndef MCU_STACK_WATCH_H
#define MCU_STACK_WATCH_H

#include <stdint.h>

#define PAINT 0xC5A5C5A5u

extern uint32_t __stack_limit;

static inline uint32_t sp_now(void) {
  uint32_t sp;
  __asm__ volatile("mov %0, sp" : "=r"(sp));
  return sp;
}

/* Paint the free stack below this function's own frame. */
static __attribute__((noinline)) void stack_paint(void) {
  uint32_t *p = &__stack_limit;
  uint32_t *end = (uint32_t *)(sp_now() - 16u);
  while (p < end) *p++ = PAINT;
}

/* Lowest written address of the painted region. */
static uint32_t stack_low_water(void) {
  const uint32_t *p = &__stack_limit;
  while (*p == PAINT) p++;
  return (uint32_t)(uintptr_t)p;
}

#endif /* MCU_STACK_WATCH_H */
