/* PIL node firmware: the whole controller node on the Cortex-M4F, on the bus over SLCAN.
 *
 * Per frame from the bus (pil_run's hook), in arrival order:
 *   a frame with the SYNC's identifier: the frames held since the previous SYNC are decoded
 *   (node_codec) into node-logic events and given to rh_node_logic_rx, the SYNC's own event
 *   to rh_node_logic_sync (the core steps there), and the answer is encoded (node_codec: E2E
 *   CRC, one alive counter per message from 0, as can_db.codec.Transmitter) and sent as
 *   WHEEL_TORQUE_CMD, CTRL_STATUS, CTRL_REFS, in that order (controller/runtime/node.py
 *   _frames). A rejected SYNC is not answered (the plant's timeout handles it).
 *   any other frame: held raw until the SYNC (at most PIL_NODE_HELD frames; an older one is
 *   handed to the node at once when the hold is full, which keeps the order and the result:
 *   the node buffers per stream itself). The diagnostic request identifier
 *   (PIL_NODE_DIAG_REQ_ID) is dropped: the Python process answers it outside the node, this
 *   firmware has no UDS server.
 * Holding the data frames raw puts their decoding inside the SYNC's instruction count, so one
 * marker pair (mcu_mark) spans a whole cycle's work: decode of the burst, validation, the
 * controller step, envelope, encoding; the UART transfer is outside it.
 *
 * SecOC: off (the plant runs with --no-secoc). CTRL_STATUS.COMPUTE_TIME is 0: the board has
 * no clock the node could read (QEMU's M-profile model has no DWT cycle counter).
 *
 * Build-time inputs (harness/bench/mcu/pil_node.py generates pil_node_config.h):
 *   MCU_CONFIG             static const rh_ctrl_config_t, the controller's configuration;
 *   PIL_NODE_MPC_EVERY     answers per full controller step, max(1, round(Ts / 10 ms));
 *   PIL_NODE_CONTROLLER_ID CTRL_STATUS.CONTROLLER_ID of the controller;
 *   PIL_NODE_DIAG_REQ_ID   the identifier the node ignores (diagnostic requests).
 *
 * Semihosting log (guest.txt), one line each:
 *   PIL node ready <rh_ctrl_init rc> <rh_node_logic_init rc>
 *   C <answered> <full step>   per SYNC, in order (the marker pairs' order): 1 0 an answer
 *                that re-allocated the held Delta M, 1 1 one that ran the full controller
 *                step, 0 0 a rejected SYNC (no answer)
 *   H <bytes>    the stack's high-water mark grew to <bytes> (painted at start, measured from
 *                the top of the stack after every SYNC, outside the marker pair)
 * Instruction marks: N_BASELINE empty pairs at start, then one pair per received SYNC.
 * Harness code: GNU C (the marker's attribute, the stack pointer's asm); static memory. */
#include <stdint.h>
#include <string.h>

#include "node_codec.h"
#include "node_logic.h"
#include "pil.h"
#include "pil_node_config.h"
#include "rhonn_core.h"
#include "semihost.h"

#define N_BASELINE 4 /* empty marker pairs: the marker's own cost, subtracted by the host */
#define PIL_NODE_HELD 32 /* raw frames held until the SYNC (a burst is 4, or 8 with SecOC) */
#define PAINT 0xC5A5C5A5u

extern uint32_t __stack_limit;
extern uint32_t __stack_top;

typedef struct {
  rh_ctrl_t ctrl;              /* the controller core's state */
  int ctrl_ok;                 /* rh_ctrl_init succeeded */
  rh_node_logic_t logic;       /* the node's per-cycle logic */
  pil_frame_t held[PIL_NODE_HELD]; /* frames since the last SYNC, oldest first */
  int n_held;
  uint8_t counter[3];          /* alive counters of the three answer frames */
  uint32_t stack_high;         /* stack high-water mark reported so far, bytes */
} pil_node_t;

__attribute__((noinline)) void mcu_mark(void) { __asm__ volatile("" ::: "memory"); }

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

/* Bytes of stack ever used, from its top down to the lowest overwritten painted word. */
static uint32_t stack_used(void) {
  const uint32_t *p = &__stack_limit;
  while (*p == PAINT) p++;
  return (uint32_t)((uintptr_t)&__stack_top - (uintptr_t)p);
}

/* RH_MON_* stream of a DBC message index, -1 for a message the node does not monitor. */
static int stream_of(int message) {
  switch (message) {
    case RH_NODE_DBC_MSG_DRIVER_INPUTS: return RH_MON_DRIVER;
    case RH_NODE_DBC_MSG_MOTION_SENSORS: return RH_MON_MOTION;
    case RH_NODE_DBC_MSG_WHEEL_SPEEDS: return RH_MON_WHEELS;
    case RH_NODE_DBC_MSG_VEHICLE_EST: return RH_MON_VEHICLE_EST;
    case RH_NODE_DBC_MSG_SYNC: return RH_MON_SYNC;
    default: return -1;
  }
}

/* The frame layer's verdict on one frame as a node-logic event (node/README.md, "Node
 * logic": decoded → DECODED with counter and values, well-formed but not monitored →
 * IGNORED, a rejection r → REJECTED with reason r - 1 and the stream of the frame's ID). */
static void frame_event(const pil_frame_t *f, rh_node_rx_t *ev) {
  rh_node_codec_decoded_t d;
  unsigned flags = (f->extended ? RH_NODE_CODEC_FLAG_EXTENDED : 0u) |
                   (f->rtr ? RH_NODE_CODEC_FLAG_REMOTE : 0u);
  rh_node_e2e_rejection_t r = rh_node_codec_decode(f->id, f->data, f->dlc, flags, &d);
  int k;
  memset(ev, 0, sizeof *ev);
  if (r == RH_NODE_E2E_OK) {
    ev->stream = stream_of(d.message);
    if (ev->stream < 0) {
      ev->kind = RH_NODE_RX_IGNORED;
      return;
    }
    ev->kind = RH_NODE_RX_DECODED;
    ev->frame.counter = d.counter;
    for (k = 0; k < (int)d.n_values && k < RH_MON_MAX_SIGNALS; k++)
      ev->frame.values[k] = d.values[k];
    return;
  }
  ev->kind = RH_NODE_RX_REJECTED;
  ev->reason = (int)r - 1;
  ev->stream = stream_of(rh_node_codec_find(f->id));
}

static void hand_over(pil_node_t *n, const pil_frame_t *f) {
  rh_node_rx_t ev;
  frame_event(f, &ev);
  (void)rh_node_logic_rx(&n->logic, &ev); /* -1 only for events it cannot place: counted */
}

/* Encode one answer frame and send it; the message's alive counter advances either way
 * (as the Transmitter's does when it encodes). */
static void send_answer(pil_node_t *n, pil_link_t *link, int slot, int message,
                        const double *values) {
  pil_frame_t f;
  memset(&f, 0, sizeof f);
  f.id = rh_node_codec_message(message)->frame_id;
  f.dlc = RH_NODE_CODEC_FRAME_LENGTH;
  (void)rh_node_codec_encode(message, values, n->counter[slot], f.data, 0);
  n->counter[slot] = (uint8_t)((n->counter[slot] + 1u) % 16u);
  (void)pil_tx_frame(link, &f); /* refused only while the host has the channel closed */
}

static void node_hook(void *node, pil_link_t *link, const pil_frame_t *rx) {
  pil_node_t *n = (pil_node_t *)node;
  rh_node_rx_t ev;
  rh_node_tx_t tx;
  double tq[5], st[7], refs[4];
  int i, answered;
  uint32_t used;

  if (!rx->extended && rx->id == PIL_NODE_DIAG_REQ_ID) return;
  if (rx->id != RH_NODE_DBC_ID_SYNC) {
    if (n->n_held == PIL_NODE_HELD) { /* full: the oldest goes to the node now */
      hand_over(n, &n->held[0]);
      memmove(&n->held[0], &n->held[1], (PIL_NODE_HELD - 1) * sizeof n->held[0]);
      n->n_held--;
    }
    n->held[n->n_held++] = *rx;
    return;
  }
  mcu_mark();
  for (i = 0; i < n->n_held; i++) hand_over(n, &n->held[i]);
  n->n_held = 0;
  frame_event(rx, &ev);
  answered = rh_node_logic_sync(&n->logic, n->ctrl_ok ? &n->ctrl : 0, &ev, 0, 0, &tx) == 1;
  if (answered) {
    tq[0] = tx.tq_nm[0];
    tq[1] = tx.tq_nm[1];
    tq[2] = tx.tq_nm[2];
    tq[3] = tx.tq_nm[3];
    tq[4] = (double)tx.echo_cycle;
    st[0] = (double)tx.mode;
    st[1] = (double)tx.fault_bits;
    st[2] = (double)tx.qp_status;
    st[3] = (double)tx.qp_iter;
    st[4] = tx.compute_time_us;
    st[5] = (double)tx.echo_cycle;
    st[6] = (double)tx.controller_id;
    refs[0] = tx.delta_m_nm;
    refs[1] = tx.yaw_rate_ref_deg_s;
    refs[2] = tx.beta_ref_deg;
    refs[3] = (double)tx.echo_cycle;
  }
  mcu_mark();
  if (answered) {
    send_answer(n, link, 0, RH_NODE_DBC_MSG_WHEEL_TORQUE_CMD, tq);
    send_answer(n, link, 1, RH_NODE_DBC_MSG_CTRL_STATUS, st);
    send_answer(n, link, 2, RH_NODE_DBC_MSG_CTRL_REFS, refs);
  }
  ln_str("C ");
  ln_dec((uint32_t)answered);
  ln_str(answered && tx.mpc_update ? " 1\n" : " 0\n");
  used = stack_used();
  if (used > n->stack_high) {
    n->stack_high = used;
    ln_str("H ");
    ln_dec(used);
    ln_str("\n");
  }
  ln_flush();
}

int main(void) {
  static pil_link_t link;
  static pil_node_t node;
  rh_node_logic_config_t cfg;
  int rc_ctrl, rc_logic, i;

  stack_paint();
  rc_ctrl = rh_ctrl_init(&node.ctrl, &MCU_CONFIG);
  node.ctrl_ok = rc_ctrl == 0;
  rh_node_logic_default_config(&cfg);
  cfg.mpc_every = PIL_NODE_MPC_EVERY;
  cfg.controller_id = PIL_NODE_CONTROLLER_ID;
  rc_logic = rh_node_logic_init(&node.logic, &cfg); /* -1: FAULT latched, still answers */
  if (pil_init(&link) != PIL_OK) {
    ln_str("PIL uart init failed\n");
    ln_flush();
    return 1;
  }
  for (i = 0; i < N_BASELINE; i++) {
    mcu_mark();
    mcu_mark();
  }
  ln_str("PIL node ready ");
  ln_dec((uint32_t)(rc_ctrl < 0 ? -rc_ctrl : rc_ctrl));
  ln_str(" ");
  ln_dec((uint32_t)(rc_logic < 0 ? -rc_logic : rc_logic));
  ln_str("\n");
  ln_flush();
  pil_run(&link, node_hook, &node);
  return 0;
}
