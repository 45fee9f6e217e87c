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
 * SecOC (built with -DPIL_NODE_SECOC and the two keys, PIL_NODE_KEY_PLANT_TO_CTRL and
 * PIL_NODE_KEY_CTRL_TO_PLANT, 16-byte initialisers): the controller's receiver and sender of
 * can_db/secoc.py ControllerSecOc. The trigger is then SYNC_AUTH: the held frames go through
 * the receiver in arrival order (the plant's driver and sensor frames and their
 * authenticators are held per stream, SYNC waits for its authenticator); an authentic SYNC
 * releases the burst's frames that verify (node_secoc, with the trip learnt from SYNC_AUTH
 * and the SYNC's cycle) as the node's released events, and the answer's torque and status
 * frames are each followed by their authenticator. Without it the node runs unsecured (the
 * plant with --no-secoc). CTRL_STATUS.COMPUTE_TIME is 0: the board has no clock the node
 * could read (QEMU's M-profile model has no DWT cycle counter).
 *
 * Build-time inputs (harness/bench/mcu/pil_node.py generates pil_node_config.h):
 *   MCU_CONFIG             static const rh_ctrl_config_t, the controller's configuration;
 *   PIL_NODE_MPC_EVERY     answers per full controller step, max(1, round(Ts / 10 ms));
 *   PIL_NODE_CONTROLLER_ID CTRL_STATUS.CONTROLLER_ID of the controller;
 *   PIL_NODE_DIAG_REQ_ID   the identifier the node ignores (diagnostic requests).
 *
 * Semihosting log (guest.txt), one line each:
 *   PIL node ready <rh_ctrl_init rc> <rh_node_logic_init rc>
 *   C <answered> <full step>   per SYNC (SecOC: per SYNC_AUTH), in order (the marker pairs'
 *                order): 1 0 an answer that re-allocated the held Delta M, 1 1 one that ran
 *                the full controller step, 0 0 no answer (a rejected SYNC, or one whose
 *                authenticator did not verify)
 *   H <bytes>    the stack's high-water mark grew to <bytes> (painted at start, measured from
 *                the top of the stack after every SYNC, outside the marker pair)
 *   R <7 counts> SecOC verdicts so far when they changed (rh_node_secoc_verdict_t order:
 *                accepted, bad_mac, stale_freshness, replay, unauthenticated, orphan_auth,
 *                unchecked_auth)
 * Instruction marks: N_BASELINE empty pairs at start, then one pair per received SYNC (with
 * SecOC: per SYNC_AUTH).
 * Harness code: GNU C (the marker's attribute, the stack pointer's asm); static memory. */
#include <stdint.h>
#include <string.h>

#include "node_codec.h"
#include "node_e2e.h"
#include "node_logic.h"
#include "node_secoc.h"
#include "pil.h"
#include "pil_node_config.h"
#include "rhonn_core.h"
#include "semihost.h"
#include "stack_watch.h"

#define N_BASELINE 4 /* empty marker pairs: the marker's own cost, subtracted by the host */
/* Buffer sizes from the bus schedule (can_db/rhonn_tv.dbc: every plant message has
 * GenMsgCycleTime 10 ms, so a lockstep burst carries each of them once: DRIVER_INPUTS,
 * MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST, SYNC, and with SecOC their five authenticators).
 * PIL_NODE_HELD: raw frames held until the trigger, one burst (4 before SYNC, 9 before
 * SYNC_AUTH); more only hands the oldest on before the trigger's marker (same order, same
 * result). PIL_NODE_SEC_HELD: per deferred stream, data frames and authenticators kept until
 * an authentic SYNC: 2 per cycle, for as many cycles as the node logic buffers per stream
 * without SecOC (RH_NODE_BURST_MAX); a fuller queue pushes its oldest out, counted
 * unauthenticated / unchecked_auth and as an eviction (RX_OVERLOAD in the answer), as
 * can_db/secoc.py does beyond its HELD (32). At an authentic SYNC the frames that verify are
 * written over the front of their stream's queue (a verified frame needs its own
 * authenticator behind it, so at most half of it) and handed to the node from there. */
#define PIL_NODE_HELD 10
#define PIL_NODE_DEFERRED 4 /* the plant's secured data streams: DRIVER_INPUTS .. VEHICLE_EST */
#define PIL_NODE_SEC_HELD (2 * RH_NODE_BURST_MAX)

extern uint32_t __stack_top;

#ifdef PIL_NODE_SECOC
/* the receiver's pending queue takes every data frame a held stream can carry: only the
 * hold pushes frames out */
typedef char pil_node_pending_fits[(RH_NODE_SECOC_PENDING >= PIL_NODE_SEC_HELD) ? 1 : -1];

/* The controller's SecOC (can_db/secoc.py ControllerSecOc): the receiver of the plant's
 * SYNC and driver/sensor frames (key plant -> controller, trip learnt from SYNC_AUTH) and the
 * sender of the torque and status authenticators (key controller -> plant). */
typedef struct {
  rh_node_cmac_key_t key_rx, key_tx;
  rh_node_secoc_rx_t rx;
  rh_node_secoc_stream_t sync_stream;
  rh_node_secoc_stream_t streams[PIL_NODE_DEFERRED];
  pil_frame_t held[PIL_NODE_DEFERRED][PIL_NODE_SEC_HELD]; /* data and authenticators */
  int n_held[PIL_NODE_DEFERRED];
  rh_node_secoc_tx_t tx[2];    /* WHEEL_TORQUE_CMD, CTRL_STATUS */
  int n_released[PIL_NODE_DEFERRED]; /* verified at the SYNC: held[d][0 .. n_released[d]) */
  int64_t evicted;             /* unverified frames pushed out of a bounded queue */
  uint32_t rejected[7];        /* by rh_node_secoc_verdict_t (ACCEPTED: accepted frames) */
  uint32_t reported[7];        /* the counts last written to the log */
} pil_secoc_t;
#endif

typedef struct {
  rh_ctrl_t ctrl;              /* the controller core's state */
  int ctrl_ok;                 /* rh_ctrl_init succeeded */
  rh_node_logic_t logic;       /* the node's per-cycle logic */
  pil_frame_t held[PIL_NODE_HELD]; /* frames since the last SYNC, oldest first */
  int n_held;
  uint8_t counter[3];          /* alive counters of the three answer frames */
  uint32_t stack_high;         /* stack high-water mark reported so far, bytes */
#ifdef PIL_NODE_SECOC
  pil_secoc_t sec;
#endif
} pil_node_t;

__attribute__((noinline)) void mcu_mark(void) { __asm__ volatile("" ::: "memory"); }

/* Bytes of stack ever used, from its top down to the lowest overwritten painted word. */
static uint32_t stack_used(void) {
  return (uint32_t)((uintptr_t)&__stack_top - stack_low_water());
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
 * (as the Transmitter's does when it encodes). out: the 8 bytes sent. */
static void send_answer(pil_node_t *n, pil_link_t *link, int slot, int message,
                        const double *values, uint8_t out[8]) {
  pil_frame_t f;
  memset(&f, 0, sizeof f);
  f.id = rh_node_codec_message(message)->frame_id;
  f.dlc = RH_NODE_CODEC_FRAME_LENGTH;
  (void)rh_node_codec_encode(message, values, n->counter[slot], f.data, 0);
  n->counter[slot] = (uint8_t)((n->counter[slot] + 1u) % 16u);
  memcpy(out, f.data, 8u);
  (void)pil_tx_frame(link, &f); /* refused only while the host has the channel closed */
}

#ifdef PIL_NODE_SECOC
#define PIL_NODE_TRIGGER_ID RH_NODE_DBC_ID_SYNC_AUTH /* an answer follows SYNC's authenticator */

static const int DEFERRED_MSG[PIL_NODE_DEFERRED] = {
    RH_NODE_DBC_MSG_DRIVER_INPUTS, RH_NODE_DBC_MSG_MOTION_SENSORS, RH_NODE_DBC_MSG_WHEEL_SPEEDS,
    RH_NODE_DBC_MSG_VEHICLE_EST};

/* Deferred stream of a data or authenticator frame ID, -1 for any other; *is_data. */
static int deferred_of(uint32_t id, int *is_data) {
  int d;
  for (d = 0; d < PIL_NODE_DEFERRED; d++) {
    const rh_node_dbc_message_t *m = rh_node_codec_message(DEFERRED_MSG[d]);
    if (id == m->frame_id || id == rh_node_dbc_messages[m->auth_message].frame_id) {
      *is_data = id == m->frame_id;
      return d;
    }
  }
  return -1;
}

static void count(pil_secoc_t *sec, rh_node_secoc_verdict_t v, uint32_t k) {
  sec->rejected[v] += k;
}

/* Forget a stream's unverified frames at the end of a burst (counted unauthenticated). */
static void drop_pending(pil_secoc_t *sec, rh_node_secoc_stream_t *s) {
  count(sec, RH_NODE_SECOC_UNAUTHENTICATED, s->pending_count);
  s->pending_count = 0u;
  s->pending_head = 0u;
}

/* An authenticator of deferred stream d on arrival, with the trip known: checked against the
 * stream's held data frames (SecOcReceiver._verify_early). 1 when the verdict is final: the
 * data frame that verified leaves the hold and, accepted, goes to the node now (into its
 * burst, as an unsecured frame would); replayed or stale, it is counted and dropped.
 * 0 when nothing verified: the authenticator is held for the SYNC. */
static int verify_early(pil_node_t *n, int d, const pil_frame_t *auth) {
  pil_secoc_t *sec = &n->sec;
  const uint8_t *data[PIL_NODE_SEC_HELD];
  size_t len[PIL_NODE_SEC_HELD];
  int at[PIL_NODE_SEC_HELD];
  size_t n_data = 0;
  int k, hit;
  uint32_t data_id = rh_node_codec_message(DEFERRED_MSG[d])->frame_id;
  rh_node_secoc_result_t res;
  pil_frame_t verified;
  if (!sec->rx.has_trip) return 0;
  for (k = 0; k < sec->n_held[d]; k++) {
    if (sec->held[d][k].id != data_id) continue;
    data[n_data] = sec->held[d][k].data;
    len[n_data] = sec->held[d][k].dlc;
    at[n_data++] = k;
  }
  hit = rh_node_secoc_verify_early(&sec->rx, &sec->streams[d], &sec->key_rx, DEFERRED_MSG[d],
                                   auth->data, auth->dlc, data, len, n_data, &res);
  if (hit < 0) return 0;
  verified = sec->held[d][at[hit]];
  memmove(&sec->held[d][at[hit]], &sec->held[d][at[hit] + 1],
          (size_t)(sec->n_held[d] - at[hit] - 1) * sizeof(pil_frame_t));
  sec->n_held[d]--;
  count(sec, res.verdict, 1u);
  if (res.verdict == RH_NODE_SECOC_ACCEPTED) hand_over(n, &verified);
  return 1;
}

/* One frame through the receiver, as SecOcReceiver.feed: a deferred data frame is held; a
 * data frame that is no classical 8-byte frame with its E2E CRC goes to the node at once
 * (rejected there); a deferred authenticator is judged at once when it verifies a held data
 * frame of a known trip (verify_early), else held; SYNC waits for its authenticator; any
 * other frame goes to the node. */
static void feed(pil_node_t *n, const pil_frame_t *f) {
  pil_secoc_t *sec = &n->sec;
  int is_data = 0;
  int d = deferred_of(f->id, &is_data);
  if (d >= 0) {
    const rh_node_dbc_message_t *m = rh_node_codec_message(DEFERRED_MSG[d]);
    if (f->rtr || f->extended) {
      if (is_data) hand_over(n, f); /* the E2E layer rejects and counts it */
      return;
    }
    if (is_data && (f->dlc != m->length || !rh_node_e2e_crc_ok(f->id, m->crc_bits, f->data))) {
      hand_over(n, f);
      return;
    }
    if (!is_data && verify_early(n, d, f)) return;
    if (sec->n_held[d] == PIL_NODE_SEC_HELD) { /* the oldest goes, unverified */
      count(sec, sec->held[d][0].id == m->frame_id ? RH_NODE_SECOC_UNAUTHENTICATED
                                                  : RH_NODE_SECOC_UNCHECKED_AUTH, 1u);
      sec->evicted++;
      memmove(&sec->held[d][0], &sec->held[d][1], (PIL_NODE_SEC_HELD - 1) * sizeof(pil_frame_t));
      sec->n_held[d]--;
    }
    sec->held[d][sec->n_held[d]++] = *f;
    return;
  }
  if (f->id == RH_NODE_DBC_ID_SYNC) {
    if (f->rtr || f->extended) { /* the node's SYNC path rejects it: no answer */
      rh_node_rx_t ev;
      rh_node_tx_t tx;
      frame_event(f, &ev);
      (void)rh_node_logic_sync(&n->logic, n->ctrl_ok ? &n->ctrl : 0, &ev, 0, 0, &tx);
      return;
    }
    if (rh_node_secoc_hold(&sec->sync_stream, f->data, f->dlc)) {
      count(sec, RH_NODE_SECOC_UNAUTHENTICATED, 1u);
      sec->evicted++;
    }
    return;
  }
  hand_over(n, f);
}

/* After an authentic SYNC: the held frames of each deferred stream, in arrival order,
 * through the pending / verify steps (SecOcReceiver._release_held); the verified data
 * frames written in order over the front of the stream's queue (slot n_released[d] <= k:
 * never one not read yet). */
static void release_held(pil_node_t *n) {
  pil_secoc_t *sec = &n->sec;
  int d, k;
  for (d = 0; d < PIL_NODE_DEFERRED; d++) {
    sec->n_released[d] = 0;
    for (k = 0; k < sec->n_held[d]; k++) {
      const pil_frame_t *f = &sec->held[d][k];
      if (f->id == rh_node_codec_message(DEFERRED_MSG[d])->frame_id) {
        if (rh_node_secoc_hold(&sec->streams[d], f->data, f->dlc)) {
          count(sec, RH_NODE_SECOC_UNAUTHENTICATED, 1u);
          sec->evicted++;
        }
      } else {
        rh_node_secoc_result_t res;
        rh_node_secoc_check_auth(&sec->rx, &sec->streams[d], &sec->key_rx, DEFERRED_MSG[d],
                                 f->data, f->dlc, 0u, &res);
        count(sec, res.verdict, 1u);
        count(sec, RH_NODE_SECOC_UNAUTHENTICATED, res.unauthenticated);
        if (res.verdict == RH_NODE_SECOC_ACCEPTED) {
          pil_frame_t *data = &sec->held[d][sec->n_released[d]++];
          memset(data, 0, sizeof *data);
          data->id = rh_node_codec_message(DEFERRED_MSG[d])->frame_id;
          data->dlc = res.data_len;
          memcpy(data->data, res.data, 8u);
        }
      }
    }
    sec->n_held[d] = 0;
    drop_pending(sec, &sec->streams[d]);
  }
}

/* SYNC_AUTH: verify the held SYNC; when authentic, release the burst's frames and answer. */
static int trigger(pil_node_t *n, const pil_frame_t *auth, rh_node_tx_t *tx) {
  pil_secoc_t *sec = &n->sec;
  rh_node_secoc_result_t res;
  rh_node_rx_t ev, rel;
  pil_frame_t sync;
  int d, k;
  rh_node_secoc_check_auth(&sec->rx, &sec->sync_stream, &sec->key_rx, RH_NODE_DBC_MSG_SYNC,
                           auth->data, auth->dlc,
                           (auth->extended ? RH_NODE_CODEC_FLAG_EXTENDED : 0u) |
                               (auth->rtr ? RH_NODE_CODEC_FLAG_REMOTE : 0u),
                           &res);
  count(sec, res.verdict, 1u);
  count(sec, RH_NODE_SECOC_UNAUTHENTICATED, res.unauthenticated);
  if (res.verdict != RH_NODE_SECOC_ACCEPTED) return 0;
  sec->rx.cycle = (uint32_t)((res.fv >> 8) & 0xFFFFFFu);
  release_held(n);
  memset(&sync, 0, sizeof sync);
  sync.id = RH_NODE_DBC_ID_SYNC;
  sync.dlc = res.data_len;
  memcpy(sync.data, res.data, 8u);
  frame_event(&sync, &ev);
  rh_node_logic_set_secoc_evicted(&n->logic, sec->evicted);
  /* rh_node_logic_sync with the released frames decoded one at a time from the queues */
  if (rh_node_logic_sync_begin(&n->logic, n->ctrl_ok ? &n->ctrl : 0, &ev) != 0) return 0;
  for (d = 0; d < PIL_NODE_DEFERRED; d++) {
    for (k = 0; k < sec->n_released[d]; k++) {
      frame_event(&sec->held[d][k], &rel);
      (void)rh_node_logic_accept(&n->logic, &rel, n->logic.last_stamp_s);
    }
  }
  return rh_node_logic_sync_end(&n->logic, n->ctrl_ok ? &n->ctrl : 0, &ev, tx) == 1;
}

/* The authenticator of an answer frame just sent (slot 0: torque, 1: status). */
static void send_auth(pil_node_t *n, pil_link_t *link, int slot, int message,
                      const uint8_t payload[8], int64_t cycle) {
  pil_frame_t f;
  int auth;
  memset(&f, 0, sizeof f);
  auth = rh_node_secoc_authenticator(&n->sec.tx[slot], &n->sec.key_tx, message, payload,
                                     n->sec.rx.trip, (uint32_t)(cycle > 0 ? cycle : 0), f.data);
  if (auth < 0) return;
  f.id = rh_node_dbc_messages[auth].frame_id;
  f.dlc = RH_NODE_CODEC_FRAME_LENGTH;
  (void)pil_tx_frame(link, &f);
}

/* Log the SecOC counts when they changed: "R accepted bad_mac stale replay unauth orphan
 * unchecked" (rh_node_secoc_verdict_t order). */
static void report_secoc(pil_secoc_t *sec) {
  int k, same = 1;
  for (k = 0; k < 7; k++) same &= sec->rejected[k] == sec->reported[k];
  if (same) return;
  memcpy(sec->reported, sec->rejected, sizeof sec->rejected);
  ln_str("R");
  for (k = 0; k < 7; k++) {
    ln_str(" ");
    ln_dec(sec->rejected[k]);
  }
  ln_str("\n");
}
#else
#define PIL_NODE_TRIGGER_ID RH_NODE_DBC_ID_SYNC

static void feed(pil_node_t *n, const pil_frame_t *f) { hand_over(n, f); }

static int trigger(pil_node_t *n, const pil_frame_t *sync, rh_node_tx_t *tx) {
  rh_node_rx_t ev;
  frame_event(sync, &ev);
  return rh_node_logic_sync(&n->logic, n->ctrl_ok ? &n->ctrl : 0, &ev, 0, 0, tx) == 1;
}
#endif

static void node_hook(void *node, pil_link_t *link, const pil_frame_t *rx) {
  pil_node_t *n = (pil_node_t *)node;
  rh_node_tx_t tx;
  double tq[5], st[7], refs[4];
  uint8_t sent[3][8];
  int i, answered;
  uint32_t used;

  if (!rx->extended && rx->id == PIL_NODE_DIAG_REQ_ID) return;
  if (rx->id != PIL_NODE_TRIGGER_ID) {
    if (n->n_held == PIL_NODE_HELD) { /* full: the oldest goes through now */
      feed(n, &n->held[0]);
      memmove(&n->held[0], &n->held[1], (PIL_NODE_HELD - 1) * sizeof n->held[0]);
      n->n_held--;
    }
    n->held[n->n_held++] = *rx;
    return;
  }
  mcu_mark();
  for (i = 0; i < n->n_held; i++) feed(n, &n->held[i]);
  n->n_held = 0;
  answered = trigger(n, rx, &tx);
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
  /* The cycle's log lines are written before its answers go out: a host that has the answer
   * finds the counts behind it in the guest log (semihosting writes before returning). */
  ln_str("C ");
  ln_dec((uint32_t)answered);
  ln_str(answered && tx.mpc_update ? " 1\n" : " 0\n");
#ifdef PIL_NODE_SECOC
  report_secoc(&n->sec);
#endif
  ln_flush();
  if (answered) { /* the order of node.py _frames, authenticators after their frames */
    send_answer(n, link, 0, RH_NODE_DBC_MSG_WHEEL_TORQUE_CMD, tq, sent[0]);
#ifdef PIL_NODE_SECOC
    send_auth(n, link, 0, RH_NODE_DBC_MSG_WHEEL_TORQUE_CMD, sent[0], tx.cycle);
#endif
    send_answer(n, link, 1, RH_NODE_DBC_MSG_CTRL_STATUS, st, sent[1]);
#ifdef PIL_NODE_SECOC
    send_auth(n, link, 1, RH_NODE_DBC_MSG_CTRL_STATUS, sent[1], tx.cycle);
#endif
    send_answer(n, link, 2, RH_NODE_DBC_MSG_CTRL_REFS, refs, sent[2]);
  }
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
#ifdef PIL_NODE_SECOC
  {
    static const uint8_t key_rx[16] = PIL_NODE_KEY_PLANT_TO_CTRL;
    static const uint8_t key_tx[16] = PIL_NODE_KEY_CTRL_TO_PLANT;
    int k;
    rh_node_cmac_init(&node.sec.key_rx, key_rx);
    rh_node_cmac_init(&node.sec.key_tx, key_tx);
    node.sec.rx.max_age_cycles = RH_NODE_SECOC_MAX_AGE_CYCLES;
    rh_node_secoc_stream_init(&node.sec.sync_stream);
    for (k = 0; k < PIL_NODE_DEFERRED; k++) rh_node_secoc_stream_init(&node.sec.streams[k]);
    rh_node_secoc_tx_init(&node.sec.tx[0]);
    rh_node_secoc_tx_init(&node.sec.tx[1]);
  }
#endif
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
