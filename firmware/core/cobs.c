/* COBS encoder/decoder (see cobs.h). */
#include "cobs.h"

static void enc_write(cobs_enc_t *e, uint16_t at, uint8_t byte)
{
    if (at < e->cap) {
        e->dst[at] = byte;
    } else {
        e->overflow = 1;
    }
}

/* Reserve the code byte of a new block. */
static void enc_open(cobs_enc_t *e)
{
    e->code_pos = e->pos++;
    e->code = 1;
    e->full = 0;
}

void cobs_enc_begin(cobs_enc_t *e, uint8_t *dst, uint16_t cap)
{
    e->dst = dst;
    e->cap = cap;
    e->pos = 0;
    e->overflow = 0;
    enc_open(e);
}

void cobs_enc_put(cobs_enc_t *e, uint8_t byte)
{
    if (e->full) {
        enc_open(e); /* opened lazily: a final full run needs no trailing code byte */
    }
    if (byte == 0u) {
        enc_write(e, e->code_pos, e->code);
        enc_open(e);
        return;
    }
    enc_write(e, e->pos++, byte);
    if (++e->code == 0xFFu) {
        enc_write(e, e->code_pos, e->code);
        e->full = 1;
    }
}

uint16_t cobs_enc_end(cobs_enc_t *e)
{
    if (!e->full) {
        enc_write(e, e->code_pos, e->code);
    }
    return e->overflow ? 0u : e->pos;
}

uint16_t cobs_encode(const uint8_t *src, uint16_t len, uint8_t *dst, uint16_t cap)
{
    cobs_enc_t e;
    cobs_enc_begin(&e, dst, cap);
    for (uint16_t i = 0; i < len; i++) {
        cobs_enc_put(&e, src[i]);
    }
    return cobs_enc_end(&e);
}

int8_t cobs_decode(const uint8_t *src, uint16_t len, uint8_t *dst, uint16_t cap,
                   uint16_t *out_len)
{
    uint16_t in = 0;
    uint16_t out = 0;
    while (in < len) {
        uint8_t code = src[in++];
        if (code == 0u || (uint16_t)(code - 1u) > (uint16_t)(len - in)) {
            return -1; /* delimiter inside the frame, or block runs past the end */
        }
        for (uint8_t k = 1; k < code; k++) {
            uint8_t b = src[in++];
            if (b == 0u || out >= cap) {
                return -1;
            }
            dst[out++] = b; /* out < in: safe in place */
        }
        if (code != 0xFFu && in < len) {
            if (out >= cap) {
                return -1;
            }
            dst[out++] = 0u;
        }
    }
    *out_len = out;
    return 0;
}
