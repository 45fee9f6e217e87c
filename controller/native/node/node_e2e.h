/* E2E protection of the node's frames: the two CRC profiles of the DBC and the receiver's
 * alive-counter check (mirrors can_db/crc.py and RxMonitor._check_counter in
 * can_db/monitor.py). No state of its own: the counter state lives in a struct the caller
 * owns, one per received message stream. */
#ifndef RH_NODE_E2E_H
#define RH_NODE_E2E_H

#include <stdint.h>

/** Why a received frame was not accepted: the values and order of can_db.codec.Rejection
 *  (RH_NODE_E2E_OK = accepted; rh_node_e2e_rejection_name gives the Python string). */
typedef enum {
    RH_NODE_E2E_OK = 0,
    RH_NODE_E2E_UNKNOWN_ID,
    RH_NODE_E2E_NOT_DATA_FRAME,
    RH_NODE_E2E_WRONG_LENGTH,
    RH_NODE_E2E_BAD_CRC,
    RH_NODE_E2E_OUT_OF_RANGE,
    RH_NODE_E2E_COUNTER_FROZEN,
    RH_NODE_E2E_COUNTER_JUMP,   /* frames missed: the frame is still accepted */
    RH_NODE_E2E_COUNTER_FAULT,
    RH_NODE_E2E_WRONG_SEQUENCE,
    RH_NODE_E2E_TIMEOUT
} rh_node_e2e_rejection_t;

#define RH_NODE_E2E_COUNTER_MODULO 16u
#define RH_NODE_E2E_MAX_DELTA_COUNTER 3u   /* CRC16 profile window (can_db/monitor.py) */
#define RH_NODE_E2E_COUNTER_FAULT_LIMIT 5u /* RxMonitor's default counter_fault_limit */

/** Alive-counter supervision state of one message stream (zero it with rh_node_e2e_counter_init). */
typedef struct {
    uint8_t has_last;     /* 0 until the first frame */
    uint8_t last_counter; /* 0..15 */
    uint8_t fault_level;  /* 0..limit */
    uint8_t window;       /* 1: CRC16 profile (counter-delta window), 0: CRC8 profile */
} rh_node_e2e_counter_t;

/** CRC-8 SAE J1850 (poly 0x1D, init 0xFF, final XOR 0xFF) of the CRC8 profile over
 *  [ID >> 8, ID & 0xFF, payload[1..7]] (can_db.crc.frame_crc). */
uint8_t rh_node_e2e_crc8(uint32_t frame_id, const uint8_t payload[8]);

/** CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, final XOR 0) of the CRC16
 *  profile over [ID >> 8, ID & 0xFF, payload[2..7]] (can_db.crc.frame_crc16). */
uint16_t rh_node_e2e_crc16(uint32_t frame_id, const uint8_t payload[8]);

/** CRC-8 SAE J1850 / CRC-16/CCITT-FALSE of arbitrary bytes (check values 0x4B / 0x29B1
 *  for "123456789"). */
uint8_t rh_node_e2e_crc8_bytes(const uint8_t *data, uint32_t len);
uint16_t rh_node_e2e_crc16_bytes(const uint8_t *data, uint32_t len);

/** Write the E2E CRC of the profile (crc_bits 8 or 16) into payload[0] (and payload[1],
 *  low byte first, for 16). */
void rh_node_e2e_seal(uint32_t frame_id, uint8_t crc_bits, uint8_t payload[8]);

/** 1 when payload carries the right CRC of its profile, else 0. */
int rh_node_e2e_crc_ok(uint32_t frame_id, uint8_t crc_bits, const uint8_t payload[8]);

/** Start a stream's counter state; window = 1 for a CRC16-profile message. */
void rh_node_e2e_counter_init(rh_node_e2e_counter_t *state, int window);

/** The alive-counter check of a decoded frame's counter (0..15), as
 *  RxMonitor._check_counter: RH_NODE_E2E_OK, or COUNTER_JUMP (accepted, counted), or a
 *  rejection (COUNTER_FROZEN, WRONG_SEQUENCE, COUNTER_FAULT). limit: the fault level at
 *  which the stream is invalid (RH_NODE_E2E_COUNTER_FAULT_LIMIT). The stored counter is
 *  always the received one. */
rh_node_e2e_rejection_t rh_node_e2e_check_counter(rh_node_e2e_counter_t *state,
                                                  uint8_t counter, uint8_t limit);

/** The Python name of a rejection ("bad_crc", ...; "ok" for RH_NODE_E2E_OK). */
const char *rh_node_e2e_rejection_name(rh_node_e2e_rejection_t reason);

#endif /* RH_NODE_E2E_H */
