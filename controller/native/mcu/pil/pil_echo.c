/* PIL echo firmware: proves the SLCAN path end to end. Every frame received from the host is
 * answered with one frame: identifier + 1 (wrapping within 11 or 29 bits), same format and
 * DLC, each data byte + 1 (mod 256); a remote frame is answered with a remote frame.
 *
 * Semihosting log: "PIL echo ready" once the UART is set up; a failed set-up prints
 * "PIL uart init failed" and exits 1. The firmware runs until QEMU is stopped.
 * Harness code: GNU C (the marker's attribute and asm). */
#include <stdint.h>

#include "pil.h"
#include "semihost.h"

#define N_BASELINE 4 /* empty marker pairs: the marker's own cost, subtracted by the host */

__attribute__((noinline)) void mcu_mark(void) { __asm__ volatile("" ::: "memory"); }

static void echo_hook(void *node, pil_link_t *link, const pil_frame_t *rx) {
  pil_frame_t tx = *rx;
  uint32_t i;
  (void)node;
  tx.id = (rx->id + 1u) & (rx->extended ? SLCAN_EXT_ID_MAX : SLCAN_STD_ID_MAX);
  for (i = 0u; i < rx->dlc; i++) tx.data[i] = (uint8_t)(rx->data[i] + 1u);
  (void)pil_tx_frame(link, &tx); /* refused only if the host closed the channel meanwhile */
}

int main(void) {
  static pil_link_t link;
  int i;
  if (pil_init(&link) != PIL_OK) {
    ln_str("PIL uart init failed\n");
    ln_flush();
    return 1;
  }
  for (i = 0; i < N_BASELINE; i++) {
    mcu_mark();
    mcu_mark();
  }
  ln_str("PIL echo ready\n");
  ln_flush();
  pil_run(&link, echo_hook, 0);
  return 0;
}
