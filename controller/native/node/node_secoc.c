/* SecOC of the node's secured frames (see node_secoc.h; the Python reference is
 * can_db/secoc.py: freshness, reconstruct, MacEngine.mac, SecOcSender.authenticator,
 * SecOcReceiver._hold_pending, _check_auth, _verify). */
#include <string.h>

#include "node_codec.h"
#include "node_dbc.h"
#include "node_secoc.h"

#define MASK(bits) ((1ull << (bits)) - 1ull)
#define OVERSIZE 9u /* pending_len of a frame longer than 8 bytes */

uint64_t rh_node_secoc_freshness(uint32_t trip, uint32_t cycle, uint32_t sub)
{
    return (((uint64_t)trip & MASK(RH_NODE_SECOC_TRIP_BITS)) << 32)
           | (((uint64_t)cycle & MASK(RH_NODE_SECOC_CYCLE_BITS)) << 8)
           | ((uint64_t)sub & MASK(RH_NODE_SECOC_SUB_BITS));
}

int64_t rh_node_secoc_reconstruct(uint32_t fv_lo, uint64_t upper)
{
    /* upper - ((upper - fv_lo) mod 2^20), Python's non-negative modulo */
    int64_t up = (int64_t)upper;
    int64_t diff = up - (int64_t)fv_lo;
    int64_t mod = (int64_t)(1ll << RH_NODE_SECOC_FV_LO_BITS);
    int64_t rem = diff % mod;
    if (rem < 0) {
        rem += mod;
    }
    return up - rem;
}

uint32_t rh_node_secoc_mac(const rh_node_cmac_key_t *key, uint32_t frame_id,
                           const uint8_t *data, size_t len, uint64_t fv)
{
    uint8_t msg[2u + 8u + 8u];
    uint8_t tag[RH_NODE_CMAC_BLOCK];
    size_t n = 0u;
    unsigned i;
    if (len > 8u) {
        len = 8u; /* callers never pass more: a classical CAN payload */
    }
    msg[n++] = (uint8_t)((frame_id >> 8) & 0xFFu);
    msg[n++] = (uint8_t)(frame_id & 0xFFu);
    for (i = 0u; i < len; ++i) {
        msg[n++] = data[i];
    }
    for (i = 0u; i < 8u; ++i) {
        msg[n++] = (uint8_t)(fv >> (56u - 8u * i));
    }
    rh_node_cmac_compute(key, msg, n, tag);
    return ((uint32_t)tag[0] << 24) | ((uint32_t)tag[1] << 16) | ((uint32_t)tag[2] << 8)
           | (uint32_t)tag[3];
}

void rh_node_secoc_tx_init(rh_node_secoc_tx_t *tx)
{
    memset(tx, 0, sizeof *tx);
}

int rh_node_secoc_authenticator(rh_node_secoc_tx_t *tx, const rh_node_cmac_key_t *key,
                                int data_message, const uint8_t payload[8], uint32_t trip,
                                uint32_t cycle, uint8_t out[8])
{
    const rh_node_dbc_message_t *msg = rh_node_codec_message(data_message);
    double values[RH_NODE_DBC_MAX_SIGNALS] = {0.0};
    uint32_t sub = 0u;
    uint64_t fv;
    uint32_t tag;
    int auth;
    memset(out, 0, 8u);
    if (msg == NULL || msg->auth_message < 0) {
        return -1;
    }
    auth = msg->auth_message;
    if (tx->has_last && tx->last_cycle == cycle) {
        sub = tx->last_sub + 1u; /* a FV is never used twice within a cycle */
    }
    tx->has_last = 1u;
    tx->last_cycle = cycle;
    tx->last_sub = sub;
    fv = rh_node_secoc_freshness(trip, cycle, sub);
    tag = rh_node_secoc_mac(key, msg->frame_id, payload, 8u, fv);
    if (data_message == RH_NODE_DBC_MSG_SYNC) {
        values[RH_NODE_DBC_SIG_SYNC_AUTH_TRIP] =
            (double)((uint64_t)trip & MASK(RH_NODE_SECOC_TRIP_BITS));
        values[RH_NODE_DBC_SIG_SYNC_AUTH_MAC] = (double)tag;
    } else {
        values[RH_NODE_DBC_AUTH_SIG_FV_LO] = (double)(fv & MASK(RH_NODE_SECOC_FV_LO_BITS));
        values[RH_NODE_DBC_AUTH_SIG_MAC] = (double)tag;
    }
    (void)rh_node_codec_encode(auth, values, tx->counter, out, NULL);
    tx->counter = (uint8_t)((tx->counter + 1u) & 0x0Fu);
    return auth;
}

void rh_node_secoc_stream_init(rh_node_secoc_stream_t *stream)
{
    memset(stream, 0, sizeof *stream);
}

/* the k-th remembered FV, oldest first */
static uint64_t history_at(const rh_node_secoc_stream_t *s, uint32_t k)
{
    return s->history[(s->history_head + k) % RH_NODE_SECOC_HISTORY];
}

int rh_node_secoc_seen(const rh_node_secoc_stream_t *stream, uint64_t fv)
{
    /* accepted FVs only grow (each is above the last), so the ring is sorted: bisect */
    uint32_t lo = 0u;
    uint32_t hi = stream->history_count;
    while (lo < hi) {
        uint32_t mid = lo + (hi - lo) / 2u;
        uint64_t v = history_at(stream, mid);
        if (v == fv) {
            return 1;
        }
        if (v < fv) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return 0;
}

static void remember(rh_node_secoc_stream_t *s, uint64_t fv)
{
    if (s->history_count == RH_NODE_SECOC_HISTORY) {
        s->history[s->history_head] = fv; /* the oldest goes */
        s->history_head = (s->history_head + 1u) % RH_NODE_SECOC_HISTORY;
    } else {
        s->history[(s->history_head + s->history_count) % RH_NODE_SECOC_HISTORY] = fv;
        s->history_count++;
    }
    s->last_fv = fv;
    s->has_last_fv = 1u;
}

int rh_node_secoc_hold(rh_node_secoc_stream_t *stream, const uint8_t *data, size_t dlc)
{
    int evicted = 0;
    uint32_t slot;
    if (stream->pending_count == RH_NODE_SECOC_PENDING) {
        stream->pending_head = (stream->pending_head + 1u) % RH_NODE_SECOC_PENDING;
        stream->pending_count--;
        evicted = 1;
    }
    slot = (stream->pending_head + stream->pending_count) % RH_NODE_SECOC_PENDING;
    memset(stream->pending[slot], 0, 8u);
    if (dlc > 8u) {
        stream->pending_len[slot] = (uint8_t)OVERSIZE;
    } else {
        if (dlc > 0u) {
            memcpy(stream->pending[slot], data, dlc);
        }
        stream->pending_len[slot] = (uint8_t)dlc;
    }
    stream->pending_count++;
    return evicted;
}

/* drop the k-th pending frame (oldest first), keeping the order of the others */
static void pending_remove(rh_node_secoc_stream_t *s, uint32_t k)
{
    uint32_t i;
    for (i = k; i + 1u < s->pending_count; ++i) {
        uint32_t to = (s->pending_head + i) % RH_NODE_SECOC_PENDING;
        uint32_t from = (s->pending_head + i + 1u) % RH_NODE_SECOC_PENDING;
        memcpy(s->pending[to], s->pending[from], 8u);
        s->pending_len[to] = s->pending_len[from];
    }
    s->pending_count--;
}

/* the full FV the pending frame slot would carry, or -1 when it cannot be judged */
static int64_t candidate_fv(const rh_node_secoc_rx_t *rx, const rh_node_secoc_stream_t *s,
                            uint32_t slot, int is_sync, const rh_node_codec_decoded_t *auth)
{
    if (is_sync) {
        rh_node_codec_decoded_t sync;
        if (rh_node_codec_decode(rh_node_dbc_messages[RH_NODE_DBC_MSG_SYNC].frame_id,
                                 s->pending[slot], s->pending_len[slot], 0u, &sync)
            != RH_NODE_E2E_OK) {
            return -1;
        }
        return (int64_t)rh_node_secoc_freshness(
            (uint32_t)auth->values[RH_NODE_DBC_SIG_SYNC_AUTH_TRIP],
            (uint32_t)sync.values[RH_NODE_DBC_SIG_SYNC_CYCLE], 0u);
    }
    if (!rx->has_trip || s->pending_len[slot] == OVERSIZE) {
        return -1;
    }
    return rh_node_secoc_reconstruct(
        (uint32_t)auth->values[RH_NODE_DBC_AUTH_SIG_FV_LO],
        rh_node_secoc_freshness(rx->trip, rx->cycle, (uint32_t)MASK(RH_NODE_SECOC_SUB_BITS)));
}

void rh_node_secoc_check_auth(rh_node_secoc_rx_t *rx, rh_node_secoc_stream_t *stream,
                              const rh_node_cmac_key_t *key, int data_message,
                              const uint8_t *auth, size_t auth_dlc, unsigned auth_flags,
                              rh_node_secoc_result_t *out)
{
    const rh_node_dbc_message_t *msg = rh_node_codec_message(data_message);
    rh_node_codec_decoded_t a;
    int is_sync = data_message == RH_NODE_DBC_MSG_SYNC;
    uint32_t tag;
    uint32_t k;
    memset(out, 0, sizeof *out);
    out->verdict = RH_NODE_SECOC_BAD_MAC;
    if (msg == NULL || msg->auth_message < 0) {
        return;
    }
    /* a corrupted authenticator cannot verify */
    if (rh_node_codec_decode(rh_node_dbc_messages[msg->auth_message].frame_id, auth, auth_dlc,
                             auth_flags, &a) != RH_NODE_E2E_OK) {
        return;
    }
    if (stream->pending_count == 0u) {
        out->verdict = RH_NODE_SECOC_ORPHAN_AUTH;
        return;
    }
    tag = (uint32_t)a.values[is_sync ? RH_NODE_DBC_SIG_SYNC_AUTH_MAC : RH_NODE_DBC_AUTH_SIG_MAC];
    for (k = 0u; k < stream->pending_count; ++k) {
        uint32_t slot = (stream->pending_head + k) % RH_NODE_SECOC_PENDING;
        int64_t fv = candidate_fv(rx, stream, slot, is_sync, &a);
        uint64_t ufv;
        int too_old;
        if (fv < 0 || rh_node_secoc_mac(key, msg->frame_id, stream->pending[slot],
                                        stream->pending_len[slot], (uint64_t)fv) != tag) {
            continue;
        }
        /* authentic: now judge its freshness */
        ufv = (uint64_t)fv;
        out->fv = ufv;
        out->data_len = stream->pending_len[slot];
        memcpy(out->data, stream->pending[slot], 8u);
        pending_remove(stream, k);
        if (rh_node_secoc_seen(stream, ufv)) {
            out->verdict = RH_NODE_SECOC_REPLAY;
            return;
        }
        too_old = !is_sync && ((ufv >> 8) & MASK(RH_NODE_SECOC_CYCLE_BITS))
                                      + (uint64_t)rx->max_age_cycles < (uint64_t)rx->cycle;
        if ((stream->has_last_fv && ufv <= stream->last_fv) || too_old) {
            out->verdict = RH_NODE_SECOC_STALE_FRESHNESS;
            return;
        }
        if (is_sync) {
            out->new_trip = (uint8_t)(rx->has_trip && (uint32_t)(ufv >> 32) != rx->trip);
            rx->trip = (uint32_t)(ufv >> 32);
            rx->has_trip = 1u;
        }
        /* older pending frames of the stream never got an authenticator */
        out->unauthenticated = stream->pending_count;
        stream->pending_count = 0u;
        stream->pending_head = 0u;
        remember(stream, ufv);
        out->verdict = RH_NODE_SECOC_ACCEPTED;
        return;
    }
}

/* the FV's cycle (bits 8..31) */
static uint64_t fv_cycle(uint64_t fv)
{
    return (fv >> 8) & MASK(RH_NODE_SECOC_CYCLE_BITS);
}

int rh_node_secoc_verify_early(const rh_node_secoc_rx_t *rx, rh_node_secoc_stream_t *stream,
                               const rh_node_cmac_key_t *key, int data_message,
                               const uint8_t *auth, size_t auth_dlc,
                               const uint8_t *const *data, const size_t *data_len, size_t n,
                               rh_node_secoc_result_t *out)
{
    const rh_node_dbc_message_t *msg = rh_node_codec_message(data_message);
    rh_node_codec_decoded_t a;
    int64_t fv;
    uint32_t tag;
    size_t k;
    memset(out, 0, sizeof *out);
    out->verdict = RH_NODE_SECOC_BAD_MAC;
    if (msg == NULL || msg->auth_message < 0 || data_message == RH_NODE_DBC_MSG_SYNC
        || !rx->has_trip || n == 0u) {
        return -1;
    }
    if (rh_node_codec_decode(rh_node_dbc_messages[msg->auth_message].frame_id, auth, auth_dlc,
                             0u, &a) != RH_NODE_E2E_OK) {
        return -1;
    }
    fv = rh_node_secoc_reconstruct(
        (uint32_t)a.values[RH_NODE_DBC_AUTH_SIG_FV_LO],
        rh_node_secoc_freshness(rx->trip, rx->cycle + rx->max_age_cycles,
                                (uint32_t)MASK(RH_NODE_SECOC_SUB_BITS)));
    if (fv < 0) {
        return -1;
    }
    tag = (uint32_t)a.values[RH_NODE_DBC_AUTH_SIG_MAC];
    for (k = 0u; k < n; ++k) {
        uint64_t ufv = (uint64_t)fv;
        if (data_len[k] > 8u
            || rh_node_secoc_mac(key, msg->frame_id, data[k], data_len[k], ufv) != tag) {
            continue;
        }
        /* authentic: the verdict is final */
        out->fv = ufv;
        out->data_len = (uint8_t)data_len[k];
        memcpy(out->data, data[k], data_len[k]);
        if (rh_node_secoc_seen(stream, ufv)) {
            out->verdict = RH_NODE_SECOC_REPLAY;
        } else if ((stream->has_last_fv && ufv <= stream->last_fv)
                   || fv_cycle(ufv) + (uint64_t)rx->max_age_cycles < (uint64_t)rx->cycle) {
            out->verdict = RH_NODE_SECOC_STALE_FRESHNESS;
        } else {
            remember(stream, ufv);
            out->verdict = RH_NODE_SECOC_ACCEPTED;
        }
        return (int)k;
    }
    return -1;
}

const char *rh_node_secoc_verdict_name(rh_node_secoc_verdict_t verdict)
{
    switch (verdict) {
    case RH_NODE_SECOC_ACCEPTED: return "accepted";
    case RH_NODE_SECOC_BAD_MAC: return "bad_mac";
    case RH_NODE_SECOC_STALE_FRESHNESS: return "stale_freshness";
    case RH_NODE_SECOC_REPLAY: return "replay";
    case RH_NODE_SECOC_UNAUTHENTICATED: return "unauthenticated";
    case RH_NODE_SECOC_ORPHAN_AUTH: return "orphan_auth";
    case RH_NODE_SECOC_UNCHECKED_AUTH: return "unchecked_auth";
    default: return "invalid";
    }
}
