/* AES-128 and AES-128-CMAC (see node_cmac.h).
 *
 * Column-wise AES on 32-bit words (FIPS-197 5.1): a state column is one word, row r in bits
 * 8r..8r+7 (little-endian packing, whatever the machine's byte order). One round of a column
 * is four lookups in one 256-entry table and three rotations: TE[x] packs the MixColumns
 * column (2 S(x), S(x), S(x), 3 S(x)) of a row-0 byte, and the byte of row r contributes the
 * same column rotated by r bytes (MixColumns is circulant). The S-box is byte 1 of TE (for
 * the key schedule and the last round, which has no MixColumns). On the Cortex-M4 a rotation
 * is free in the second operand of EOR, so a round is about 16 byte extracts, 16 loads and
 * 20 EORs.
 *
 * TE was computed from the definitions (FIPS-197 5.1.1: S(x) = the affine map with 0x63 of
 * the inverse of x in GF(2^8) mod x^8 + x^4 + x^3 + x + 1; 5.1.3: products by 2 and 3 in the
 * same field), written by this project. 1 KiB of flash. */
#include "node_cmac.h"

static const uint32_t TE[256] = {
    0xA56363C6u, 0x847C7CF8u, 0x997777EEu, 0x8D7B7BF6u, 0x0DF2F2FFu, 0xBD6B6BD6u,
    0xB16F6FDEu, 0x54C5C591u, 0x50303060u, 0x03010102u, 0xA96767CEu, 0x7D2B2B56u,
    0x19FEFEE7u, 0x62D7D7B5u, 0xE6ABAB4Du, 0x9A7676ECu, 0x45CACA8Fu, 0x9D82821Fu,
    0x40C9C989u, 0x877D7DFAu, 0x15FAFAEFu, 0xEB5959B2u, 0xC947478Eu, 0x0BF0F0FBu,
    0xECADAD41u, 0x67D4D4B3u, 0xFDA2A25Fu, 0xEAAFAF45u, 0xBF9C9C23u, 0xF7A4A453u,
    0x967272E4u, 0x5BC0C09Bu, 0xC2B7B775u, 0x1CFDFDE1u, 0xAE93933Du, 0x6A26264Cu,
    0x5A36366Cu, 0x413F3F7Eu, 0x02F7F7F5u, 0x4FCCCC83u, 0x5C343468u, 0xF4A5A551u,
    0x34E5E5D1u, 0x08F1F1F9u, 0x937171E2u, 0x73D8D8ABu, 0x53313162u, 0x3F15152Au,
    0x0C040408u, 0x52C7C795u, 0x65232346u, 0x5EC3C39Du, 0x28181830u, 0xA1969637u,
    0x0F05050Au, 0xB59A9A2Fu, 0x0907070Eu, 0x36121224u, 0x9B80801Bu, 0x3DE2E2DFu,
    0x26EBEBCDu, 0x6927274Eu, 0xCDB2B27Fu, 0x9F7575EAu, 0x1B090912u, 0x9E83831Du,
    0x742C2C58u, 0x2E1A1A34u, 0x2D1B1B36u, 0xB26E6EDCu, 0xEE5A5AB4u, 0xFBA0A05Bu,
    0xF65252A4u, 0x4D3B3B76u, 0x61D6D6B7u, 0xCEB3B37Du, 0x7B292952u, 0x3EE3E3DDu,
    0x712F2F5Eu, 0x97848413u, 0xF55353A6u, 0x68D1D1B9u, 0x00000000u, 0x2CEDEDC1u,
    0x60202040u, 0x1FFCFCE3u, 0xC8B1B179u, 0xED5B5BB6u, 0xBE6A6AD4u, 0x46CBCB8Du,
    0xD9BEBE67u, 0x4B393972u, 0xDE4A4A94u, 0xD44C4C98u, 0xE85858B0u, 0x4ACFCF85u,
    0x6BD0D0BBu, 0x2AEFEFC5u, 0xE5AAAA4Fu, 0x16FBFBEDu, 0xC5434386u, 0xD74D4D9Au,
    0x55333366u, 0x94858511u, 0xCF45458Au, 0x10F9F9E9u, 0x06020204u, 0x817F7FFEu,
    0xF05050A0u, 0x443C3C78u, 0xBA9F9F25u, 0xE3A8A84Bu, 0xF35151A2u, 0xFEA3A35Du,
    0xC0404080u, 0x8A8F8F05u, 0xAD92923Fu, 0xBC9D9D21u, 0x48383870u, 0x04F5F5F1u,
    0xDFBCBC63u, 0xC1B6B677u, 0x75DADAAFu, 0x63212142u, 0x30101020u, 0x1AFFFFE5u,
    0x0EF3F3FDu, 0x6DD2D2BFu, 0x4CCDCD81u, 0x140C0C18u, 0x35131326u, 0x2FECECC3u,
    0xE15F5FBEu, 0xA2979735u, 0xCC444488u, 0x3917172Eu, 0x57C4C493u, 0xF2A7A755u,
    0x827E7EFCu, 0x473D3D7Au, 0xAC6464C8u, 0xE75D5DBAu, 0x2B191932u, 0x957373E6u,
    0xA06060C0u, 0x98818119u, 0xD14F4F9Eu, 0x7FDCDCA3u, 0x66222244u, 0x7E2A2A54u,
    0xAB90903Bu, 0x8388880Bu, 0xCA46468Cu, 0x29EEEEC7u, 0xD3B8B86Bu, 0x3C141428u,
    0x79DEDEA7u, 0xE25E5EBCu, 0x1D0B0B16u, 0x76DBDBADu, 0x3BE0E0DBu, 0x56323264u,
    0x4E3A3A74u, 0x1E0A0A14u, 0xDB494992u, 0x0A06060Cu, 0x6C242448u, 0xE45C5CB8u,
    0x5DC2C29Fu, 0x6ED3D3BDu, 0xEFACAC43u, 0xA66262C4u, 0xA8919139u, 0xA4959531u,
    0x37E4E4D3u, 0x8B7979F2u, 0x32E7E7D5u, 0x43C8C88Bu, 0x5937376Eu, 0xB76D6DDAu,
    0x8C8D8D01u, 0x64D5D5B1u, 0xD24E4E9Cu, 0xE0A9A949u, 0xB46C6CD8u, 0xFA5656ACu,
    0x07F4F4F3u, 0x25EAEACFu, 0xAF6565CAu, 0x8E7A7AF4u, 0xE9AEAE47u, 0x18080810u,
    0xD5BABA6Fu, 0x887878F0u, 0x6F25254Au, 0x722E2E5Cu, 0x241C1C38u, 0xF1A6A657u,
    0xC7B4B473u, 0x51C6C697u, 0x23E8E8CBu, 0x7CDDDDA1u, 0x9C7474E8u, 0x211F1F3Eu,
    0xDD4B4B96u, 0xDCBDBD61u, 0x868B8B0Du, 0x858A8A0Fu, 0x907070E0u, 0x423E3E7Cu,
    0xC4B5B571u, 0xAA6666CCu, 0xD8484890u, 0x05030306u, 0x01F6F6F7u, 0x120E0E1Cu,
    0xA36161C2u, 0x5F35356Au, 0xF95757AEu, 0xD0B9B969u, 0x91868617u, 0x58C1C199u,
    0x271D1D3Au, 0xB99E9E27u, 0x38E1E1D9u, 0x13F8F8EBu, 0xB398982Bu, 0x33111122u,
    0xBB6969D2u, 0x70D9D9A9u, 0x898E8E07u, 0xA7949433u, 0xB69B9B2Du, 0x221E1E3Cu,
    0x92878715u, 0x20E9E9C9u, 0x49CECE87u, 0xFF5555AAu, 0x78282850u, 0x7ADFDFA5u,
    0x8F8C8C03u, 0xF8A1A159u, 0x80898909u, 0x170D0D1Au, 0xDABFBF65u, 0x31E6E6D7u,
    0xC6424284u, 0xB86868D0u, 0xC3414182u, 0xB0999929u, 0x772D2D5Au, 0x110F0F1Eu,
    0xCBB0B07Bu, 0xFC5454A8u, 0xD6BBBB6Du, 0x3A16162Cu,
};

#define AES_ROUNDS 10u
#define CMAC_RB 0x87u /* SP 800-38B: R_128 = 0^120 || 10000111 */

#define ROTL(x, n) (((x) << (n)) | ((x) >> (32u - (n))))
#define BYTE(w, r) (((w) >> (8u * (r))) & 0xFFu)
#define SBOX(x) ((TE[(x)] >> 8) & 0xFFu)

static uint32_t load_column(const uint8_t b[4])
{
    return (uint32_t)b[0] | ((uint32_t)b[1] << 8) | ((uint32_t)b[2] << 16)
           | ((uint32_t)b[3] << 24);
}

static void store_column(uint32_t w, uint8_t b[4])
{
    b[0] = (uint8_t)w;
    b[1] = (uint8_t)(w >> 8);
    b[2] = (uint8_t)(w >> 16);
    b[3] = (uint8_t)(w >> 24);
}

void rh_node_cmac_aes_expand(const uint8_t key[16], uint32_t round_keys[44])
{
    uint32_t rcon = 0x01u;
    unsigned i;
    for (i = 0u; i < 4u; ++i) {
        round_keys[i] = load_column(&key[4u * i]);
    }
    for (i = 4u; i < RH_NODE_CMAC_ROUND_KEY_WORDS; ++i) {
        uint32_t t = round_keys[i - 1u];
        if (i % 4u == 0u) {
            /* RotWord, SubWord, Rcon (in row 0, the low byte) */
            t = (SBOX(BYTE(t, 1u)) | (SBOX(BYTE(t, 2u)) << 8) | (SBOX(BYTE(t, 3u)) << 16)
                 | (SBOX(BYTE(t, 0u)) << 24))
                ^ rcon;
            rcon = ((rcon << 1) ^ ((rcon & 0x80u) != 0u ? 0x1Bu : 0x00u)) & 0xFFu;
        }
        round_keys[i] = round_keys[i - 4u] ^ t;
    }
}

/* One full round of column c: SubBytes, ShiftRows (row r from column c + r), MixColumns. */
#define ROUND_COLUMN(s0, s1, s2, s3, rk)                                                   \
    (TE[BYTE(s0, 0u)] ^ ROTL(TE[BYTE(s1, 1u)], 8u) ^ ROTL(TE[BYTE(s2, 2u)], 16u)          \
     ^ ROTL(TE[BYTE(s3, 3u)], 24u) ^ (rk))

/* The last round of column c: SubBytes and ShiftRows only. */
#define LAST_COLUMN(s0, s1, s2, s3, rk)                                                    \
    ((SBOX(BYTE(s0, 0u)) | (SBOX(BYTE(s1, 1u)) << 8) | (SBOX(BYTE(s2, 2u)) << 16)         \
      | (SBOX(BYTE(s3, 3u)) << 24))                                                        \
     ^ (rk))

void rh_node_cmac_aes_encrypt(const uint32_t round_keys[44], const uint8_t in[16],
                              uint8_t out[16])
{
    const uint32_t *rk = round_keys;
    uint32_t s0 = load_column(&in[0]) ^ rk[0];
    uint32_t s1 = load_column(&in[4]) ^ rk[1];
    uint32_t s2 = load_column(&in[8]) ^ rk[2];
    uint32_t s3 = load_column(&in[12]) ^ rk[3];
    unsigned round;
    for (round = 1u; round < AES_ROUNDS; ++round) {
        uint32_t t0, t1, t2, t3;
        rk += 4;
        t0 = ROUND_COLUMN(s0, s1, s2, s3, rk[0]);
        t1 = ROUND_COLUMN(s1, s2, s3, s0, rk[1]);
        t2 = ROUND_COLUMN(s2, s3, s0, s1, rk[2]);
        t3 = ROUND_COLUMN(s3, s0, s1, s2, rk[3]);
        s0 = t0;
        s1 = t1;
        s2 = t2;
        s3 = t3;
    }
    rk += 4;
    store_column(LAST_COLUMN(s0, s1, s2, s3, rk[0]), &out[0]);
    store_column(LAST_COLUMN(s1, s2, s3, s0, rk[1]), &out[4]);
    store_column(LAST_COLUMN(s2, s3, s0, s1, rk[2]), &out[8]);
    store_column(LAST_COLUMN(s3, s0, s1, s2, rk[3]), &out[12]);
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
    size_t n = (len + 15u) / 16u; /* blocks; the empty message is one padded block */
    size_t i, j, off, tail;
    const uint8_t *subkey;
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
    off = 16u * (n - 1u);
    tail = len - off; /* its bytes, 0..16 */
    subkey = tail == 16u ? ctx->k1 : ctx->k2;
    for (j = 0u; j < tail; ++j) {
        x[j] ^= msg[off + j];
    }
    if (tail < 16u) {
        x[tail] ^= 0x80u;
    }
    for (j = 0u; j < 16u; ++j) {
        x[j] ^= subkey[j];
    }
    rh_node_cmac_aes_encrypt(ctx->round_keys, x, tag);
}
