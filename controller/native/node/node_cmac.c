/* AES-128 and AES-128-CMAC (see node_cmac.h). The S-box was computed from its definition
 * (FIPS-197 5.1.1: inverse in GF(2^8), then the affine map with 0x63). */
#include <string.h>

#include "node_cmac.h"

static const uint8_t SBOX[256] = {
    0x63u, 0x7Cu, 0x77u, 0x7Bu, 0xF2u, 0x6Bu, 0x6Fu, 0xC5u,
    0x30u, 0x01u, 0x67u, 0x2Bu, 0xFEu, 0xD7u, 0xABu, 0x76u,
    0xCAu, 0x82u, 0xC9u, 0x7Du, 0xFAu, 0x59u, 0x47u, 0xF0u,
    0xADu, 0xD4u, 0xA2u, 0xAFu, 0x9Cu, 0xA4u, 0x72u, 0xC0u,
    0xB7u, 0xFDu, 0x93u, 0x26u, 0x36u, 0x3Fu, 0xF7u, 0xCCu,
    0x34u, 0xA5u, 0xE5u, 0xF1u, 0x71u, 0xD8u, 0x31u, 0x15u,
    0x04u, 0xC7u, 0x23u, 0xC3u, 0x18u, 0x96u, 0x05u, 0x9Au,
    0x07u, 0x12u, 0x80u, 0xE2u, 0xEBu, 0x27u, 0xB2u, 0x75u,
    0x09u, 0x83u, 0x2Cu, 0x1Au, 0x1Bu, 0x6Eu, 0x5Au, 0xA0u,
    0x52u, 0x3Bu, 0xD6u, 0xB3u, 0x29u, 0xE3u, 0x2Fu, 0x84u,
    0x53u, 0xD1u, 0x00u, 0xEDu, 0x20u, 0xFCu, 0xB1u, 0x5Bu,
    0x6Au, 0xCBu, 0xBEu, 0x39u, 0x4Au, 0x4Cu, 0x58u, 0xCFu,
    0xD0u, 0xEFu, 0xAAu, 0xFBu, 0x43u, 0x4Du, 0x33u, 0x85u,
    0x45u, 0xF9u, 0x02u, 0x7Fu, 0x50u, 0x3Cu, 0x9Fu, 0xA8u,
    0x51u, 0xA3u, 0x40u, 0x8Fu, 0x92u, 0x9Du, 0x38u, 0xF5u,
    0xBCu, 0xB6u, 0xDAu, 0x21u, 0x10u, 0xFFu, 0xF3u, 0xD2u,
    0xCDu, 0x0Cu, 0x13u, 0xECu, 0x5Fu, 0x97u, 0x44u, 0x17u,
    0xC4u, 0xA7u, 0x7Eu, 0x3Du, 0x64u, 0x5Du, 0x19u, 0x73u,
    0x60u, 0x81u, 0x4Fu, 0xDCu, 0x22u, 0x2Au, 0x90u, 0x88u,
    0x46u, 0xEEu, 0xB8u, 0x14u, 0xDEu, 0x5Eu, 0x0Bu, 0xDBu,
    0xE0u, 0x32u, 0x3Au, 0x0Au, 0x49u, 0x06u, 0x24u, 0x5Cu,
    0xC2u, 0xD3u, 0xACu, 0x62u, 0x91u, 0x95u, 0xE4u, 0x79u,
    0xE7u, 0xC8u, 0x37u, 0x6Du, 0x8Du, 0xD5u, 0x4Eu, 0xA9u,
    0x6Cu, 0x56u, 0xF4u, 0xEAu, 0x65u, 0x7Au, 0xAEu, 0x08u,
    0xBAu, 0x78u, 0x25u, 0x2Eu, 0x1Cu, 0xA6u, 0xB4u, 0xC6u,
    0xE8u, 0xDDu, 0x74u, 0x1Fu, 0x4Bu, 0xBDu, 0x8Bu, 0x8Au,
    0x70u, 0x3Eu, 0xB5u, 0x66u, 0x48u, 0x03u, 0xF6u, 0x0Eu,
    0x61u, 0x35u, 0x57u, 0xB9u, 0x86u, 0xC1u, 0x1Du, 0x9Eu,
    0xE1u, 0xF8u, 0x98u, 0x11u, 0x69u, 0xD9u, 0x8Eu, 0x94u,
    0x9Bu, 0x1Eu, 0x87u, 0xE9u, 0xCEu, 0x55u, 0x28u, 0xDFu,
    0x8Cu, 0xA1u, 0x89u, 0x0Du, 0xBFu, 0xE6u, 0x42u, 0x68u,
    0x41u, 0x99u, 0x2Du, 0x0Fu, 0xB0u, 0x54u, 0xBBu, 0x16u,
};

#define AES_ROUNDS 10u
#define CMAC_RB 0x87u /* SP 800-38B: R_128 = 0^120 || 10000111 */

/* multiplication by x in GF(2^8) modulo x^8 + x^4 + x^3 + x + 1 */
static uint8_t xtime(uint8_t b)
{
    return (uint8_t)((uint8_t)(b << 1) ^ ((b & 0x80u) != 0u ? 0x1Bu : 0x00u));
}

void rh_node_cmac_aes_expand(const uint8_t key[16], uint8_t round_keys[176])
{
    uint8_t rcon = 0x01u;
    unsigned i;
    memcpy(round_keys, key, RH_NODE_CMAC_KEY_BYTES);
    for (i = 16u; i < RH_NODE_CMAC_ROUND_KEY_BYTES; i += 4u) {
        uint8_t t0 = round_keys[i - 4u], t1 = round_keys[i - 3u];
        uint8_t t2 = round_keys[i - 2u], t3 = round_keys[i - 1u];
        if (i % 16u == 0u) {
            /* RotWord, SubWord, Rcon */
            uint8_t first = t0;
            t0 = (uint8_t)(SBOX[t1] ^ rcon);
            t1 = SBOX[t2];
            t2 = SBOX[t3];
            t3 = SBOX[first];
            rcon = xtime(rcon);
        }
        round_keys[i] = (uint8_t)(round_keys[i - 16u] ^ t0);
        round_keys[i + 1u] = (uint8_t)(round_keys[i - 15u] ^ t1);
        round_keys[i + 2u] = (uint8_t)(round_keys[i - 14u] ^ t2);
        round_keys[i + 3u] = (uint8_t)(round_keys[i - 13u] ^ t3);
    }
}

static void add_round_key(uint8_t s[16], const uint8_t *rk)
{
    unsigned i;
    for (i = 0u; i < 16u; ++i) {
        s[i] ^= rk[i];
    }
}

/* SubBytes and ShiftRows together; the state is column-major (s[4c + r] = row r, col c) */
static void sub_shift(uint8_t s[16])
{
    uint8_t t[16];
    unsigned c, r;
    for (c = 0u; c < 4u; ++c) {
        for (r = 0u; r < 4u; ++r) {
            t[4u * c + r] = SBOX[s[4u * ((c + r) & 3u) + r]];
        }
    }
    memcpy(s, t, 16u);
}

static void mix_columns(uint8_t s[16])
{
    unsigned c;
    for (c = 0u; c < 4u; ++c) {
        uint8_t *col = &s[4u * c];
        uint8_t a0 = col[0], a1 = col[1], a2 = col[2], a3 = col[3];
        uint8_t all = (uint8_t)(a0 ^ a1 ^ a2 ^ a3);
        col[0] = (uint8_t)(a0 ^ all ^ xtime((uint8_t)(a0 ^ a1)));
        col[1] = (uint8_t)(a1 ^ all ^ xtime((uint8_t)(a1 ^ a2)));
        col[2] = (uint8_t)(a2 ^ all ^ xtime((uint8_t)(a2 ^ a3)));
        col[3] = (uint8_t)(a3 ^ all ^ xtime((uint8_t)(a3 ^ a0)));
    }
}

void rh_node_cmac_aes_encrypt(const uint8_t round_keys[176], const uint8_t in[16],
                              uint8_t out[16])
{
    uint8_t s[16];
    unsigned round;
    memcpy(s, in, 16u);
    add_round_key(s, round_keys);
    for (round = 1u; round < AES_ROUNDS; ++round) {
        sub_shift(s);
        mix_columns(s);
        add_round_key(s, &round_keys[16u * round]);
    }
    sub_shift(s);
    add_round_key(s, &round_keys[16u * AES_ROUNDS]);
    memcpy(out, s, 16u);
}

/* out = in << 1 (as a 128-bit big-endian number), XOR Rb when the top bit was set */
static void subkey_double(const uint8_t in[16], uint8_t out[16])
{
    uint8_t carry = 0u;
    unsigned i;
    for (i = 16u; i-- > 0u;) {
        uint8_t b = in[i];
        out[i] = (uint8_t)((uint8_t)(b << 1) | carry);
        carry = (uint8_t)(b >> 7);
    }
    if ((in[0] & 0x80u) != 0u) {
        out[15] ^= CMAC_RB;
    }
}

void rh_node_cmac_init(rh_node_cmac_key_t *ctx, const uint8_t key[16])
{
    uint8_t l[16] = {0};
    rh_node_cmac_aes_expand(key, ctx->round_keys);
    rh_node_cmac_aes_encrypt(ctx->round_keys, l, l);
    subkey_double(l, ctx->k1);
    subkey_double(ctx->k1, ctx->k2);
}

void rh_node_cmac_compute(const rh_node_cmac_key_t *ctx, const uint8_t *msg, size_t len,
                          uint8_t tag[16])
{
    uint8_t x[16] = {0};
    uint8_t last[16];
    size_t n = (len + 15u) / 16u; /* blocks; the empty message is one padded block */
    size_t i, j;
    int complete = (len > 0u) && (len % 16u == 0u);
    if (n == 0u) {
        n = 1u;
    }
    for (i = 0u; i + 1u < n; ++i) {
        for (j = 0u; j < 16u; ++j) {
            x[j] ^= msg[16u * i + j];
        }
        rh_node_cmac_aes_encrypt(ctx->round_keys, x, x);
    }
    /* last block: complete -> XOR K1; else pad with 10..0 and XOR K2 */
    for (j = 0u; j < 16u; ++j) {
        size_t at = 16u * (n - 1u) + j;
        if (complete) {
            last[j] = (uint8_t)(msg[at] ^ ctx->k1[j]);
        } else {
            uint8_t byte = at < len ? msg[at] : (at == len ? 0x80u : 0x00u);
            last[j] = (uint8_t)(byte ^ ctx->k2[j]);
        }
    }
    for (j = 0u; j < 16u; ++j) {
        x[j] ^= last[j];
    }
    rh_node_cmac_aes_encrypt(ctx->round_keys, x, tag);
}
