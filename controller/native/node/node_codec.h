/* Encode and decode the node's frames from the DBC tables (generated at build time by
 * dbc_gen.py: node_dbc.h), with the E2E CRC and alive counter: the same bytes and verdicts
 * as can_db.codec.Codec (encode saturates at the DBC limits, NaN encodes as the in-range
 * value nearest 0; decode checks frame kind, ID, length, CRC, then every signal's range).
 *
 * Physical values are double whatever RH_FLOAT32 says: the 32-bit MACs and the 24-bit SYNC
 * cycle need more than a float's 24-bit mantissa, and the Python codec is the float64
 * oracle. The node converts to real_t where it computes. */
#ifndef RH_NODE_CODEC_H
#define RH_NODE_CODEC_H

#include <stddef.h>
#include <stdint.h>

#include "node_dbc.h"
#include "node_e2e.h"

#define RH_NODE_CODEC_FRAME_LENGTH 8u

/* frame kind flags of rh_node_codec_decode: any of them makes a NOT_DATA_FRAME */
#define RH_NODE_CODEC_FLAG_EXTENDED 0x1u
#define RH_NODE_CODEC_FLAG_REMOTE 0x2u
#define RH_NODE_CODEC_FLAG_ERROR 0x4u
#define RH_NODE_CODEC_FLAG_FD 0x8u

/** A decoded frame (or the detail of a rejection). */
typedef struct {
    int message;        /* RH_NODE_DBC_MSG_* index, -1 for an unknown ID */
    uint8_t counter;    /* alive counter 0..15 (valid when accepted) */
    uint8_t n_values;   /* signals of the message (CRC and ALIVE excluded) */
    double values[RH_NODE_DBC_MAX_SIGNALS]; /* physical values, DBC units, signal order */
    int bad_signal;     /* OUT_OF_RANGE: index of the first signal out of range, else -1 */
    double bad_value;   /* OUT_OF_RANGE: its physical value (DBC unit) */
} rh_node_codec_decoded_t;

/** Index of the message with 11-bit ID frame_id, or -1. */
int rh_node_codec_find(uint32_t frame_id);

/** The table row of message index (NULL when out of range). */
const rh_node_dbc_message_t *rh_node_codec_message(int message);

/** Validate and decode one frame (never fails on any bytes or ID): RH_NODE_E2E_OK with
 *  out filled, or the rejection (UNKNOWN_ID, NOT_DATA_FRAME, WRONG_LENGTH, BAD_CRC,
 *  OUT_OF_RANGE) in can_db.codec.Codec.decode's order. dlc: bytes in data (0..64);
 *  flags: RH_NODE_CODEC_FLAG_*. */
rh_node_e2e_rejection_t rh_node_codec_decode(uint32_t frame_id, const uint8_t *data,
                                             size_t dlc, unsigned flags,
                                             rh_node_codec_decoded_t *out);

/** Encode message (RH_NODE_DBC_MSG_*) from physical values[] (its n_signals values in
 *  signal order, DBC units; pass 0.0 for a signal not set) and the alive counter (mod 16)
 *  into out[8] with the E2E CRC. Values beyond the DBC range saturate, NaN encodes as the
 *  in-range value nearest 0; *saturated (may be NULL) gets a bit per such signal (bit k =
 *  signal k). Returns 0, or -1 for an unknown message index or NULL values (out zeroed). */
int rh_node_codec_encode(int message, const double *values, uint8_t counter,
                         uint8_t out[8], uint32_t *saturated);

#endif /* RH_NODE_CODEC_H */
