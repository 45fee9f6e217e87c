/* Polled driver of the Arm CMSDK APB UART (Cortex-M System Design Kit TRM, Arm DDI 0479,
 * "APB UART"): 8N1, a one-byte transmit and a one-byte receive buffer, no FIFO, no flow
 * control. Used as UART0 of the MPS2 AN385/AN386 FPGA images (AN386 is the AN385 image with a
 * Cortex-M4; base addresses as in QEMU's hw/arm/mps2.c, which models the board:
 * UART0..4 at 0x40004000, 0x40005000, 0x40006000, 0x40007000, 0x40009000; APB clock 25 MHz).
 *
 * Polled: the caller must read often enough that a byte is not overwritten by the next (on a
 * real part at 115 200 bit/s that is every 86 us; QEMU holds the next byte back until the
 * buffer is read, so nothing is lost there). Overruns are counted, not hidden. */
#ifndef PIL_CMSDK_UART_H
#define PIL_CMSDK_UART_H

#include <stdint.h>

#define CMSDK_UART0_BASE 0x40004000u
#define MPS2_APB_CLOCK_HZ 25000000u

/* Register block (offsets 0x00..0x10). */
typedef struct {
  volatile uint32_t data;       /* 0x00 RX byte (read) / TX byte (write) */
  volatile uint32_t state;      /* 0x04 bit 0 TX full, 1 RX full, 2 TX overrun, 3 RX overrun (W1C) */
  volatile uint32_t ctrl;       /* 0x08 bit 0 TX enable, 1 RX enable, 2..5 interrupt enables */
  volatile uint32_t intstatus;  /* 0x0C interrupt status / clear (W1C) */
  volatile uint32_t bauddiv;    /* 0x10 APB clock / baud rate, >= 16 */
} cmsdk_uart_regs_t;

#define CMSDK_UART_STATE_TX_FULL 0x1u
#define CMSDK_UART_STATE_RX_FULL 0x2u
#define CMSDK_UART_STATE_TX_OVERRUN 0x4u
#define CMSDK_UART_STATE_RX_OVERRUN 0x8u
#define CMSDK_UART_CTRL_TX_EN 0x1u
#define CMSDK_UART_CTRL_RX_EN 0x2u

/* Driver state (caller-owned; the register block's address as an integer, no pointer). */
typedef struct {
  uint32_t base;         /* register block address, e.g. CMSDK_UART0_BASE */
  uint32_t rx_overruns;  /* receive bytes lost (RX overrun seen), counted at each read */
} cmsdk_uart_t;

/* Program the baud divider (clock_hz / baud_bps, at least 16) and enable TX and RX with
 * interrupts off. Returns 0, or -1 when the divider would be below 16 (nothing written). */
int cmsdk_uart_init(cmsdk_uart_t *u, uint32_t base, uint32_t clock_hz, uint32_t baud_bps);

/* 1 when a received byte is waiting, else 0. */
int cmsdk_uart_rx_ready(const cmsdk_uart_t *u);

/* Non-blocking read: 1 and *byte set when a byte was waiting, else 0. */
int cmsdk_uart_getc(cmsdk_uart_t *u, uint8_t *byte);

/* Blocking write of one byte (waits while the transmit buffer is full). */
void cmsdk_uart_putc(const cmsdk_uart_t *u, uint8_t byte);

/* Blocking write of n bytes. */
void cmsdk_uart_write(const cmsdk_uart_t *u, const char *bytes, uint32_t n);

#endif /* PIL_CMSDK_UART_H */
