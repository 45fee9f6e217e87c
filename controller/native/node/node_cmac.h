/* AES-128 (FIPS-197) and AES-128-CMAC (NIST SP 800-38B, RFC 4493), written for the node:
 * column-wise AES on 32-bit words with one constant 256-entry table (node_cmac.c; no
 * third-party code), encryption only (CMAC needs no decryption). State lives in the key
 * struct the caller owns. */
#ifndef RH_NODE_CMAC_H
#define RH_NODE_CMAC_H

#include <stddef.h>
#include <stdint.h>

#define RH_NODE_CMAC_BLOCK 16u
#define RH_NODE_CMAC_KEY_BYTES 16u
#define RH_NODE_CMAC_ROUND_KEY_WORDS 44u /* 11 round keys of AES-128, 4 columns each */

/** An expanded AES-128 key with its two CMAC subkeys (no pointers: copyable). */
typedef struct {
    uint32_t round_keys[RH_NODE_CMAC_ROUND_KEY_WORDS]; /* columns, row r in bits 8r.. */
    uint8_t k1[RH_NODE_CMAC_BLOCK]; /* CMAC subkey for a complete last block */
    uint8_t k2[RH_NODE_CMAC_BLOCK]; /* CMAC subkey for a padded last block */
} rh_node_cmac_key_t;

/** AES-128 key expansion (FIPS-197 5.2) into 44 column words: word i holds bytes 4i..4i+3
 *  of the byte-wise schedule, byte 4i + r in bits 8r..8r+7. */
void rh_node_cmac_aes_expand(const uint8_t key[16], uint32_t round_keys[44]);

/** One AES-128 block encryption with expanded round keys (in and out may alias). */
void rh_node_cmac_aes_encrypt(const uint32_t round_keys[44], const uint8_t in[16],
                              uint8_t out[16]);

/** Expand key and derive the CMAC subkeys K1, K2 (SP 800-38B 6.1). */
void rh_node_cmac_init(rh_node_cmac_key_t *ctx, const uint8_t key[16]);

/** AES-128-CMAC of msg[0..len) into tag[16] (SP 800-38B 6.2; len 0 allowed, msg may then
 *  be NULL). */
void rh_node_cmac_compute(const rh_node_cmac_key_t *ctx, const uint8_t *msg, size_t len,
                          uint8_t tag[16]);

#endif /* RH_NODE_CMAC_H */
