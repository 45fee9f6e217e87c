/* Encode and decode the node's frames (see node_codec.h). The arithmetic is the Python
 * codec's, operation for operation (can_db/codegen.py), so the doubles come out the same:
 * encode clamps the physical value, rounds (phys - offset) / scale half to even (Python's
 * round), clamps the raw value; decode computes raw * scale + offset and checks it against
 * [minimum - 1e-9, maximum + 1e-9]. */
#include <math.h>
#include <string.h>

#include "node_codec.h"

int rh_node_codec_find(uint32_t frame_id)
{
    int i;
    for (i = 0; i < RH_NODE_DBC_N_MESSAGES; ++i) {
        if (rh_node_dbc_messages[i].frame_id == frame_id) {
            return i;
        }
    }
    return -1;
}

const rh_node_dbc_message_t *rh_node_codec_message(int message)
{
    if (message < 0 || message >= RH_NODE_DBC_N_MESSAGES) {
        return NULL;
    }
    return &rh_node_dbc_messages[message];
}

rh_node_e2e_rejection_t rh_node_codec_decode(uint32_t frame_id, const uint8_t *data,
                                             size_t dlc, unsigned flags,
                                             rh_node_codec_decoded_t *out)
{
    const rh_node_dbc_message_t *msg;
    int64_t raw[RH_NODE_DBC_MAX_SIGNALS] = {0};
    unsigned k;
    out->message = -1;
    out->counter = 0u;
    out->n_values = 0u;
    out->bad_signal = -1;
    out->bad_value = 0.0;
    if ((flags & (RH_NODE_CODEC_FLAG_EXTENDED | RH_NODE_CODEC_FLAG_REMOTE
                  | RH_NODE_CODEC_FLAG_ERROR | RH_NODE_CODEC_FLAG_FD)) != 0u) {
        return RH_NODE_E2E_NOT_DATA_FRAME;
    }
    out->message = rh_node_codec_find(frame_id);
    msg = rh_node_codec_message(out->message);
    if (msg == NULL) {
        return RH_NODE_E2E_UNKNOWN_ID;
    }
    out->n_values = msg->n_signals;
    if (dlc != msg->length || data == NULL) {
        return RH_NODE_E2E_WRONG_LENGTH;
    }
    if (!rh_node_e2e_crc_ok(frame_id, msg->crc_bits, data)) {
        return RH_NODE_E2E_BAD_CRC;
    }
    msg->unpack(data, raw);
    for (k = 0u; k < msg->n_signals; ++k) {
        const rh_node_dbc_signal_t *sig = &msg->signals[k];
        double phys = (double)raw[k] * sig->scale + sig->offset;
        /* written as "not within" so a NaN would be out of range too */
        if (!(sig->lo_tol <= phys && phys <= sig->hi_tol)) {
            out->bad_signal = (int)k;
            out->bad_value = phys;
            return RH_NODE_E2E_OUT_OF_RANGE;
        }
        out->values[k] = phys;
    }
    /* ALIVE: the low nibble of the byte after the CRC */
    out->counter = (uint8_t)(data[msg->crc_bits / 8u] & 0x0Fu);
    return RH_NODE_E2E_OK;
}

/* the raw value of one physical value (Python: clamp, round half to even, clamp raw) */
static int64_t encode_signal(const rh_node_dbc_signal_t *sig, double phys, int *saturated)
{
    double scaled;
    int64_t raw;
    *saturated = 1;
    if (phys != phys) {
        phys = sig->nan_phys;
    } else if (phys > sig->maximum) {
        phys = sig->maximum;
    } else if (phys < sig->minimum) {
        phys = sig->minimum;
    } else {
        *saturated = 0;
    }
    /* rint rounds half to even in the default rounding mode, like Python's round() */
    scaled = rint((phys - sig->offset) / sig->scale);
    raw = (int64_t)scaled;
    if (raw > sig->raw_max) {
        raw = sig->raw_max;
    } else if (raw < sig->raw_min) {
        raw = sig->raw_min;
    }
    return raw;
}

int rh_node_codec_encode(int message, const double *values, uint8_t counter,
                         uint8_t out[8], uint32_t *saturated)
{
    const rh_node_dbc_message_t *msg = rh_node_codec_message(message);
    int64_t raw[RH_NODE_DBC_MAX_SIGNALS] = {0};
    uint32_t sat = 0u;
    unsigned k;
    memset(out, 0, RH_NODE_CODEC_FRAME_LENGTH);
    if (saturated != NULL) {
        *saturated = 0u;
    }
    if (msg == NULL || values == NULL) {
        return -1;
    }
    for (k = 0u; k < msg->n_signals; ++k) {
        int sat_k;
        raw[k] = encode_signal(&msg->signals[k], values[k], &sat_k);
        sat |= (uint32_t)sat_k << k;
    }
    msg->pack(raw, (uint8_t)(counter & 0x0Fu), out);
    rh_node_e2e_seal(msg->frame_id, msg->crc_bits, out);
    if (saturated != NULL) {
        *saturated = sat;
    }
    return 0;
}
