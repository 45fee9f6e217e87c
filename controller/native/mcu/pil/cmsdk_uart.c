/* Polled CMSDK APB UART driver (see cmsdk_uart.h). */
#include "cmsdk_uart.h"

/* The register block at an address (MMIO: the one place an integer becomes a pointer). */
static cmsdk_uart_regs_t *regs(uint32_t base) { return (cmsdk_uart_regs_t *)(uintptr_t)base; }

int cmsdk_uart_init(cmsdk_uart_t *u, uint32_t base, uint32_t clock_hz, uint32_t baud_bps) {
  uint32_t div = baud_bps > 0u ? clock_hz / baud_bps : 0u;
  cmsdk_uart_regs_t *r = regs(base);
  if (div < 16u) return -1;
  u->base = base;
  u->rx_overruns = 0u;
  r->ctrl = 0u;
  r->bauddiv = div;
  r->state = CMSDK_UART_STATE_TX_OVERRUN | CMSDK_UART_STATE_RX_OVERRUN; /* W1C: clear both */
  r->ctrl = CMSDK_UART_CTRL_TX_EN | CMSDK_UART_CTRL_RX_EN;
  return 0;
}

int cmsdk_uart_rx_ready(const cmsdk_uart_t *u) {
  return (regs(u->base)->state & CMSDK_UART_STATE_RX_FULL) != 0u;
}

int cmsdk_uart_getc(cmsdk_uart_t *u, uint8_t *byte) {
  cmsdk_uart_regs_t *r = regs(u->base);
  uint32_t state = r->state;
  if (state & CMSDK_UART_STATE_RX_OVERRUN) {
    u->rx_overruns++;
    r->state = CMSDK_UART_STATE_RX_OVERRUN;
  }
  if (!(state & CMSDK_UART_STATE_RX_FULL)) return 0;
  *byte = (uint8_t)(r->data & 0xFFu);
  return 1;
}

void cmsdk_uart_putc(const cmsdk_uart_t *u, uint8_t byte) {
  cmsdk_uart_regs_t *r = regs(u->base);
  while (r->state & CMSDK_UART_STATE_TX_FULL) {
  }
  r->data = byte;
}

void cmsdk_uart_write(const cmsdk_uart_t *u, const char *bytes, uint32_t n) {
  uint32_t i;
  for (i = 0u; i < n; i++) cmsdk_uart_putc(u, (uint8_t)bytes[i]);
}
