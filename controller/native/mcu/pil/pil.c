/* Processor-in-the-loop link over SLCAN on UART0 (see pil.h). */
#include "pil.h"

#include <stddef.h>

#ifdef PIL_INSN_MARKS
void mcu_mark(void); /* the firmware main's marker; the QEMU plugin logs each entry */
#define PIL_MARK() mcu_mark()
#else
#define PIL_MARK() ((void)0)
#endif

int pil_init(pil_link_t *link) {
  link->rx_frames = 0u;
  link->tx_frames = 0u;
  link->tx_refused = 0u;
  slcan_init(&link->codec);
  if (cmsdk_uart_init(&link->uart, CMSDK_UART0_BASE, MPS2_APB_CLOCK_HZ, PIL_UART_BAUD_BPS) != 0)
    return PIL_ERR_UART;
  return PIL_OK;
}

int pil_rx_frame(pil_link_t *link, pil_frame_t *frame) {
  char reply[SLCAN_OUT_MAX];
  size_t reply_len;
  uint8_t byte;
  uint32_t i;
  int got = 0;

  for (i = 0u; i < PIL_RX_BYTES_MAX && !got; i++) {
    slcan_event_t ev;
    if (!cmsdk_uart_rx_ready(&link->uart)) break;
    PIL_MARK();
    (void)cmsdk_uart_getc(&link->uart, &byte);
    ev = slcan_feed(&link->codec, byte, frame, reply, &reply_len);
    if (reply_len > 0u) cmsdk_uart_write(&link->uart, reply, (uint32_t)reply_len);
    if (ev == SLCAN_EV_FRAME) {
      link->rx_frames++;
      got = 1;
    }
    PIL_MARK();
  }
  return got;
}

int pil_tx_frame(pil_link_t *link, const pil_frame_t *frame) {
  char line[SLCAN_OUT_MAX];
  size_t n;
  int rc = PIL_OK;

  PIL_MARK();
  if (!slcan_is_open(&link->codec)) {
    rc = PIL_ERR_CLOSED;
  } else {
    n = slcan_format(frame, line);
    if (n == 0u) {
      rc = PIL_ERR_FRAME;
    } else {
      cmsdk_uart_write(&link->uart, line, (uint32_t)n);
      link->tx_frames++;
    }
  }
  if (rc != PIL_OK) link->tx_refused++;
  PIL_MARK();
  return rc;
}

void pil_run(pil_link_t *link, pil_step_hook_t hook, void *node) {
  pil_frame_t rx;
  for (;;) {
    if (pil_rx_frame(link, &rx)) hook(node, link, &rx);
  }
}
