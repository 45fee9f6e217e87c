/* Processor-in-the-loop link: the node's CAN frames over SLCAN on UART0 of the MPS2 AN386.
 *
 * The firmware is the "adapter" end of an SLCAN (Lawicel ASCII) serial line: the host opens
 * the channel (O\r), sends the bus's frames as t/T lines and reads the node's frames back as
 * t/T lines (slcan.h has the command set). QEMU carries UART0 to a loopback TCP socket
 * (harness/run/pil_link.py), where python-can's slcan interface is the host end.
 *
 * Frame I/O for the node:
 *   pil_rx_frame  non-blocking: reads the bytes waiting on the UART (at most PIL_RX_BYTES_MAX
 *                 per call), answers every complete command line itself, returns 1 with the
 *                 first complete frame line, else 0;
 *   pil_tx_frame  formats one frame and writes it (blocking on the UART's one-byte buffer);
 *                 refused while the host has the channel closed.
 *
 * Step hook (what the node integration implements), run by pil_run:
 *   void hook(void *node, pil_link_t *link, const pil_frame_t *rx)
 * is called once for every frame received from the bus, in arrival order, and sends its
 * answers with pil_tx_frame(link, ...) before it returns. There is no clock on the MCU side:
 * the host's frames are the time base, so the node decides from the frames when a control
 * cycle's inputs are complete (e.g. the plant's last sensor frame of a cycle) and runs its
 * controller step then. The hook must not block; frames arriving meanwhile wait in the
 * UART / the host's socket (QEMU holds bytes back until the guest reads them).
 *
 * Static memory: the caller owns the pil_link_t (no pointers inside; copyable). Built with
 * -DPIL_INSN_MARKS, the link calls mcu_mark() (provided by the firmware main) right before
 * and after the handling of each received byte and around each pil_tx_frame, so the QEMU
 * instruction-count plugin can count the link's work without the idle polling. */
#ifndef PIL_PIL_H
#define PIL_PIL_H

#include <stdint.h>

#include "cmsdk_uart.h"
#include "slcan.h"

#define PIL_UART_BAUD_BPS 115200u  /* nominal; QEMU's socket backend ignores it */
#define PIL_RX_BYTES_MAX 64u       /* bytes handled per pil_rx_frame call (bounds its time) */

#define PIL_OK 0
#define PIL_ERR_CLOSED (-1)  /* the host has the channel closed (listen-only counts as open:
                                frames to the host are allowed then) */
#define PIL_ERR_FRAME (-2)   /* identifier out of range or DLC > 8 */
#define PIL_ERR_UART (-3)    /* UART set-up refused (baud divider below 16) */

typedef slcan_frame_t pil_frame_t;

/* Link state (caller-owned). */
typedef struct {
  cmsdk_uart_t uart;
  slcan_t codec;
  uint32_t rx_frames;   /* frames received from the host */
  uint32_t tx_frames;   /* frames sent to the host */
  uint32_t tx_refused;  /* pil_tx_frame calls refused (channel closed or bad frame) */
} pil_link_t;

/* The node's step hook (see above). */
typedef void (*pil_step_hook_t)(void *node, pil_link_t *link, const pil_frame_t *rx);

/* UART0 at PIL_UART_BAUD_BPS, codec reset (channel closed). PIL_OK or PIL_ERR_UART. */
int pil_init(pil_link_t *link);

/* 1 and *frame filled when a frame from the host is complete, else 0 (never blocks). */
int pil_rx_frame(pil_link_t *link, pil_frame_t *frame);

/* Send one frame to the host: PIL_OK, PIL_ERR_CLOSED or PIL_ERR_FRAME. */
int pil_tx_frame(pil_link_t *link, const pil_frame_t *frame);

/* Poll forever, calling hook(node, link, rx) once per received frame. */
void pil_run(pil_link_t *link, pil_step_hook_t hook, void *node);

#endif /* PIL_PIL_H */
