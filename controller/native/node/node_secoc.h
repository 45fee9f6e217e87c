/* SecOC of the node's secured frames, as can_db/secoc.py: freshness value
 * FV = TRIP << 32 | cycle << 8 | sub, the 32-bit truncated AES-128-CMAC over
 * ID (2 bytes BE) || payload (8) || FV (8 BE), the authenticator frame a sender builds, and
 * the receiver's verdict on an authenticator against the pending data frames of its stream
 * (SecOcReceiver._check_auth / _verify / _hold_pending) with the per-stream freshness memory
 * (_Stream) in a struct the caller owns. The deferred holding of the plant's burst until its
 * SYNC (SecOcReceiver._held) is the node logic's: it calls these in the same order. */
#ifndef RH_NODE_SECOC_H
#define RH_NODE_SECOC_H

#include <stddef.h>
#include <stdint.h>

#include "node_cmac.h"

#define RH_NODE_SECOC_MAC_BITS 32u
#define RH_NODE_SECOC_FV_LO_BITS 20u
#define RH_NODE_SECOC_SUB_BITS 8u
#define RH_NODE_SECOC_CYCLE_BITS 24u
#define RH_NODE_SECOC_TRIP_BITS 20u    /* can_db/secoc_keys.py TRIP_BITS */
#define RH_NODE_SECOC_MAX_AGE_CYCLES 10u /* forward window, cycles of 10 ms */
/* unverified data frames kept per stream while their authenticator is awaited; 16 as
 * can_db/secoc.py PENDING. A smaller value (the PIL firmware's: what its held burst can
 * carry) only pushes the oldest out sooner, counted unauthenticated as any other. */
#ifndef RH_NODE_SECOC_PENDING
#define RH_NODE_SECOC_PENDING 16u
#endif
/* accepted FVs remembered per stream, to tell a replay from a merely stale FV; 4096 as
 * can_db/secoc.py (32 KiB a stream). A smaller value (the PIL firmware's: 16) only turns a
 * replay of a frame older than the last HISTORY accepted ones from REPLAY into
 * STALE_FRESHNESS: it is rejected either way. */
#ifndef RH_NODE_SECOC_HISTORY
#define RH_NODE_SECOC_HISTORY 4096u
#endif

/** Verdicts: the values of can_db.secoc.SecRejection, with ACCEPTED = 0. */
typedef enum {
    RH_NODE_SECOC_ACCEPTED = 0,
    RH_NODE_SECOC_BAD_MAC,
    RH_NODE_SECOC_STALE_FRESHNESS,
    RH_NODE_SECOC_REPLAY,
    RH_NODE_SECOC_UNAUTHENTICATED,
    RH_NODE_SECOC_ORPHAN_AUTH,
    RH_NODE_SECOC_UNCHECKED_AUTH
} rh_node_secoc_verdict_t;

/** Sender state of one secured data frame: last (cycle, sub) used and the alive counter
 *  of its authenticator frame (zero-initialise, or rh_node_secoc_tx_init). */
typedef struct {
    uint8_t has_last;
    uint8_t counter;     /* next ALIVE of the authenticator, 0..15 */
    uint32_t last_cycle; /* SYNC cycle of the last authenticator */
    uint32_t last_sub;   /* its index within that cycle */
} rh_node_secoc_tx_t;

/** Receiver state of one secured data stream (_Stream): pending data frames in arrival
 *  order, the last accepted FV and the last RH_NODE_SECOC_HISTORY accepted FVs (strictly
 *  increasing, a ring). */
typedef struct {
    uint8_t pending[RH_NODE_SECOC_PENDING][8];
    uint8_t pending_len[RH_NODE_SECOC_PENDING]; /* bytes; 9 = longer than 8 (never verifies) */
    uint32_t pending_head;  /* index of the oldest pending frame */
    uint32_t pending_count;
    uint8_t has_last_fv;
    uint64_t last_fv;
    uint64_t history[RH_NODE_SECOC_HISTORY];
    uint32_t history_head;  /* index of the oldest remembered FV */
    uint32_t history_count;
} rh_node_secoc_stream_t;

/** What the receiver knows of the freshness master (SecOcReceiver.trip / .cycle). */
typedef struct {
    uint8_t has_trip;        /* 0 until a trip is known (own, or learnt from SYNC) */
    uint32_t trip;           /* plant's trip counter */
    uint32_t cycle;          /* freshest cycle the sender can have answered */
    uint32_t max_age_cycles; /* forward window, cycles (RH_NODE_SECOC_MAX_AGE_CYCLES) */
} rh_node_secoc_rx_t;

/** The verdict on one authenticator frame. */
typedef struct {
    rh_node_secoc_verdict_t verdict; /* ACCEPTED, BAD_MAC, ORPHAN_AUTH, REPLAY or STALE */
    uint32_t unauthenticated; /* pending data frames dropped unauthenticated by this call */
    uint64_t fv;              /* FV of the authentic pair (ACCEPTED, REPLAY, STALE) */
    uint8_t data[8];          /* ACCEPTED: the data frame released */
    uint8_t data_len;
    uint8_t new_trip;         /* ACCEPTED SYNC whose trip differs from the known one */
} rh_node_secoc_result_t;

/** FV = trip << 32 | cycle << 8 | sub, each masked to its width. */
uint64_t rh_node_secoc_freshness(uint32_t trip, uint32_t cycle, uint32_t sub);

/** Largest FV <= upper whose low 20 bits are fv_lo; negative when there is none. */
int64_t rh_node_secoc_reconstruct(uint32_t fv_lo, uint64_t upper);

/** The 32-bit MAC (most significant bits of the CMAC) over ID (2 bytes BE) || data[0..len)
 *  || FV (8 bytes BE); len <= 8. */
uint32_t rh_node_secoc_mac(const rh_node_cmac_key_t *key, uint32_t frame_id,
                           const uint8_t *data, size_t len, uint64_t fv);

void rh_node_secoc_tx_init(rh_node_secoc_tx_t *tx);

/** The authenticator frame of the secured data frame (data_message: RH_NODE_DBC_MSG_*,
 *  payload: its 8 encoded bytes) for (trip, cycle), as SecOcSender.authenticator: sub
 *  counts the frames of the ID within one cycle. Returns the authenticator's message index
 *  (out[8] holds it, CRC and counter included), or -1 when data_message is not secured. */
int rh_node_secoc_authenticator(rh_node_secoc_tx_t *tx, const rh_node_cmac_key_t *key,
                                int data_message, const uint8_t payload[8], uint32_t trip,
                                uint32_t cycle, uint8_t out[8]);

void rh_node_secoc_stream_init(rh_node_secoc_stream_t *stream);

/** 1 when fv is among the remembered accepted FVs of the stream. */
int rh_node_secoc_seen(const rh_node_secoc_stream_t *stream, uint64_t fv);

/** Hold a received secured data frame until its authenticator (dlc bytes of data, not NULL
 *  when dlc > 0). Returns 1 when the oldest pending frame was pushed out (counted
 *  unauthenticated), else 0. Only classical data frames come here: a remote, error or
 *  extended frame of a secured ID goes to the E2E layer, which rejects it (as
 *  SecOcReceiver.feed passes it on). */
int rh_node_secoc_hold(rh_node_secoc_stream_t *stream, const uint8_t *data, size_t dlc);

/** Judge an authenticator frame (auth: auth_dlc bytes, auth_flags: RH_NODE_CODEC_FLAG_*)
 *  of data_message against the stream's pending frames, oldest first: BAD_MAC when it does
 *  not decode or no pending frame verifies, ORPHAN_AUTH with none pending, REPLAY /
 *  STALE_FRESHNESS for an authentic but not fresh pair, else ACCEPTED (the stream remembers
 *  the FV; older pending frames are dropped unauthenticated; an accepted SYNC sets the
 *  trip in rx). */
void rh_node_secoc_check_auth(rh_node_secoc_rx_t *rx, rh_node_secoc_stream_t *stream,
                              const rh_node_cmac_key_t *key, int data_message,
                              const uint8_t *auth, size_t auth_dlc, unsigned auth_flags,
                              rh_node_secoc_result_t *out);

/** Early verdict on an authenticator (auth: auth_dlc bytes, a classical frame) of a deferred
 *  data stream before its burst's SYNC has verified (SecOcReceiver._verify_early): with the
 *  trip known, the FV is reconstructed up to rx->max_age_cycles cycles ahead of rx->cycle
 *  and checked against the n candidate data frames (data[k]: data_len[k] bytes, the
 *  stream's held data frames in arrival order). Returns the index of the first candidate
 *  that verifies, its verdict in *out: ACCEPTED (the FV remembered; the caller passes the
 *  frame on now), REPLAY or STALE_FRESHNESS (counted by the caller, the frame dropped); or
 *  -1 when none verifies, the trip is unknown or the authenticator does not decode: it is
 *  then held and judged with rh_node_secoc_check_auth once the SYNC verified. The stream's
 *  pending frames are not touched. */
int rh_node_secoc_verify_early(const rh_node_secoc_rx_t *rx, rh_node_secoc_stream_t *stream,
                               const rh_node_cmac_key_t *key, int data_message,
                               const uint8_t *auth, size_t auth_dlc,
                               const uint8_t *const *data, const size_t *data_len, size_t n,
                               rh_node_secoc_result_t *out);

/** The Python name of a verdict ("bad_mac", ...; "accepted" for ACCEPTED). */
const char *rh_node_secoc_verdict_name(rh_node_secoc_verdict_t verdict);

#endif /* RH_NODE_SECOC_H */
