/* A test-only miniature controller node on the C frame layer, run as its own process by
 * tests/test_native_node_peer.py: frames in on stdin, frames and verdicts out on stdout.
 *
 * Input lines:  "<id hex> <payload hex>"  (one received CAN frame; "-" for an empty payload)
 * Output lines: "RX <id hex> <verdict>"    for each received frame (E2E or SecOC verdict,
 *                                          "held" for a SYNC awaiting its authenticator)
 *               "TX <id hex> <payload hex>" for each frame the node sends
 *
 * The node: DRIVER_INPUTS is decoded and its alive counter checked (E2E only); SYNC is held
 * until SYNC_AUTH verifies (key plant->ctrl, trip learnt from it); an authentic SYNC is
 * answered with WHEEL_TORQUE_CMD (every wheel ACCEPT_PEDAL * 4 Nm, ECHO_CYCLE = cycle mod
 * 256) and its WHEEL_TORQUE_AUTH (key ctrl->plant). argv: the two keys as 32 hex digits. */
#include <stdio.h>
#include <string.h>

#include "node_codec.h"
#include "node_secoc.h"

static int parse_hex(const char *text, uint8_t *out, size_t max)
{
    size_t n = 0u;
    unsigned byte;
    if (strcmp(text, "-") == 0) {
        return 0;
    }
    while (n < max && sscanf(text + 2u * n, "%2x", &byte) == 1) {
        out[n++] = (uint8_t)byte;
    }
    return (int)n;
}

static void print_frame(uint32_t id, const uint8_t *data)
{
    unsigned i;
    printf("TX %03X ", (unsigned)id);
    for (i = 0u; i < 8u; ++i) {
        printf("%02X", data[i]);
    }
    printf("\n");
}

int main(int argc, char **argv)
{
    static rh_node_secoc_stream_t sync_stream; /* 32 KiB: static, not on the stack */
    rh_node_cmac_key_t key_rx, key_tx;
    rh_node_secoc_rx_t rx = {0u, 0u, 0u, RH_NODE_SECOC_MAX_AGE_CYCLES};
    rh_node_secoc_tx_t torque_tx;
    rh_node_e2e_counter_t driver_counter;
    uint8_t key[16];
    uint8_t torque_counter = 0u;
    double pedal = 0.0;
    char line[256];
    char payload_hex[200];
    unsigned id;
    if (argc != 3 || parse_hex(argv[1], key, 16u) != 16) {
        fprintf(stderr, "usage: peer KEY_PLANT_TO_CTRL KEY_CTRL_TO_PLANT\n");
        return 2;
    }
    rh_node_cmac_init(&key_rx, key);
    if (parse_hex(argv[2], key, 16u) != 16) {
        fprintf(stderr, "bad key\n");
        return 2;
    }
    rh_node_cmac_init(&key_tx, key);
    rh_node_secoc_stream_init(&sync_stream);
    rh_node_secoc_tx_init(&torque_tx);
    rh_node_e2e_counter_init(&driver_counter, 1);
    while (fgets(line, sizeof line, stdin) != NULL) {
        uint8_t data[64];
        int dlc;
        if (sscanf(line, "%x %199s", &id, payload_hex) != 2) {
            continue;
        }
        dlc = parse_hex(payload_hex, data, sizeof data);
        if (id == RH_NODE_DBC_ID_SYNC) {
            (void)rh_node_secoc_hold(&sync_stream, data, (size_t)dlc);
            printf("RX %03X held\n", id);
        } else if (id == RH_NODE_DBC_ID_SYNC_AUTH) {
            rh_node_secoc_result_t res;
            rh_node_codec_decoded_t sync;
            rh_node_secoc_check_auth(&rx, &sync_stream, &key_rx, RH_NODE_DBC_MSG_SYNC, data,
                                     (size_t)dlc, 0u, &res);
            printf("RX %03X %s\n", id, rh_node_secoc_verdict_name(res.verdict));
            if (res.verdict == RH_NODE_SECOC_ACCEPTED
                && rh_node_codec_decode(RH_NODE_DBC_ID_SYNC, res.data, res.data_len, 0u, &sync)
                       == RH_NODE_E2E_OK) {
                uint32_t cycle = (uint32_t)sync.values[RH_NODE_DBC_SIG_SYNC_CYCLE];
                double values[RH_NODE_DBC_MAX_SIGNALS] = {0.0};
                uint8_t torque[8], auth[8];
                unsigned w;
                for (w = 0u; w < 4u; ++w) {
                    values[RH_NODE_DBC_SIG_WHEEL_TORQUE_CMD_TQ_FL + w] = pedal * 4.0;
                }
                values[RH_NODE_DBC_SIG_WHEEL_TORQUE_CMD_ECHO_CYCLE] = (double)(cycle & 0xFFu);
                (void)rh_node_codec_encode(RH_NODE_DBC_MSG_WHEEL_TORQUE_CMD, values,
                                           torque_counter, torque, NULL);
                torque_counter = (uint8_t)((torque_counter + 1u) & 0x0Fu);
                (void)rh_node_secoc_authenticator(&torque_tx, &key_tx,
                                                  RH_NODE_DBC_MSG_WHEEL_TORQUE_CMD, torque,
                                                  rx.trip, cycle, auth);
                print_frame(RH_NODE_DBC_ID_WHEEL_TORQUE_CMD, torque);
                print_frame(RH_NODE_DBC_ID_WHEEL_TORQUE_AUTH, auth);
            }
        } else {
            rh_node_codec_decoded_t dec;
            rh_node_e2e_rejection_t verdict = rh_node_codec_decode(id, data, (size_t)dlc, 0u,
                                                                   &dec);
            if (verdict == RH_NODE_E2E_OK && dec.message == RH_NODE_DBC_MSG_DRIVER_INPUTS) {
                verdict = rh_node_e2e_check_counter(&driver_counter, dec.counter,
                                                    RH_NODE_E2E_COUNTER_FAULT_LIMIT);
                if (verdict == RH_NODE_E2E_OK || verdict == RH_NODE_E2E_COUNTER_JUMP) {
                    pedal = dec.values[RH_NODE_DBC_SIG_DRIVER_INPUTS_ACCEL_PEDAL];
                }
            }
            printf("RX %03X %s\n", id, rh_node_e2e_rejection_name(verdict));
        }
        fflush(stdout);
    }
    return 0;
}
