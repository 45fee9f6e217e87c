/* Cortex-M4F bare-metal startup for the MCU harness: vector table, reset handler (FPU on via
 * CPACR, .data copied from flash, .bss zeroed, main), fault handlers that report and exit.
 * Harness code: GNU C (attributes, inline asm), not the core's C99 rules. */
#include <stdint.h>

#include "semihost.h"

extern uint32_t __data_load, __data_start, __data_end, __bss_start, __bss_end, __stack_top;
extern int main(void);

void Reset_Handler(void) __attribute__((noreturn));
static void Fault_Handler(void) __attribute__((noreturn));

#define SCB_CPACR (*(volatile uint32_t *)0xE000ED88u)
#define SCB_CFSR (*(volatile uint32_t *)0xE000ED28u)
#define SCB_HFSR (*(volatile uint32_t *)0xE000ED2Cu)

__attribute__((section(".vectors"), used)) static void (*const vectors[16])(void) = {
    (void (*)(void))&__stack_top, /* initial SP */
    Reset_Handler,                /* reset */
    Fault_Handler,                /* NMI */
    Fault_Handler,                /* HardFault */
    Fault_Handler,                /* MemManage */
    Fault_Handler,                /* BusFault */
    Fault_Handler,                /* UsageFault */
    0, 0, 0, 0,
    Fault_Handler, /* SVCall */
    Fault_Handler, /* DebugMon */
    0,
    Fault_Handler, /* PendSV */
    Fault_Handler, /* SysTick */
};

void Reset_Handler(void) {
  uint32_t *src, *dst;
  /* CP10/CP11 full access (FPU on) before any floating-point instruction. */
  SCB_CPACR |= (0xFu << 20);
  __asm__ volatile("dsb\n\tisb" ::: "memory");
  for (src = &__data_load, dst = &__data_start; dst < &__data_end;) *dst++ = *src++;
  for (dst = &__bss_start; dst < &__bss_end;) *dst++ = 0u;
  sh_exit(main());
}

static void Fault_Handler(void) {
  uint32_t ipsr;
  __asm__ volatile("mrs %0, ipsr" : "=r"(ipsr));
  ln_str("FAULT exception ");
  ln_dec(ipsr & 0x1ffu);
  ln_str(" CFSR ");
  ln_hex32(SCB_CFSR);
  ln_str(" HFSR ");
  ln_hex32(SCB_HFSR);
  ln_str("\n");
  ln_flush();
  sh_exit(1);
}
