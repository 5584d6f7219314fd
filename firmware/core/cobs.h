/* Consistent Overhead Byte Stuffing (minimal variant: a final full 254-byte run gets no extra
 * 0x01 code byte; the decoder accepts both forms). The 0x00 frame delimiter is not part of the
 * encoding: callers append it. */
#ifndef SMA_COBS_H
#define SMA_COBS_H
#include <stdint.h>

/* Worst-case encoded size of n input bytes (without the delimiter). */
#define COBS_MAX_ENCODED(n) ((n) + (n) / 254u + 1u)

/* Incremental encoder: encode bytes one by one straight into dst (no staging buffer). */
typedef struct {
    uint8_t *dst;
    uint16_t cap;      /* size of dst, bytes */
    uint16_t pos;      /* next write position */
    uint16_t code_pos; /* position of the pending code byte */
    uint8_t code;      /* 1 + bytes in the current block */
    uint8_t full;      /* last block closed at 254 bytes, next block not opened yet */
    uint8_t overflow;  /* dst too small: result invalid */
} cobs_enc_t;

void cobs_enc_begin(cobs_enc_t *e, uint8_t *dst, uint16_t cap);
void cobs_enc_put(cobs_enc_t *e, uint8_t byte);
/* Finish; returns the encoded length, or 0 if dst was too small. */
uint16_t cobs_enc_end(cobs_enc_t *e);

/* Encode len bytes; returns the encoded length (>= 1), or 0 if cap is too small. */
uint16_t cobs_encode(const uint8_t *src, uint16_t len, uint8_t *dst, uint16_t cap);
/* Decode len bytes (without delimiter) into dst; dst == src (in place) is allowed.
 * Returns 0 and sets *out_len on success, -1 on invalid COBS (a 0x00 byte, a block running past
 * the end) or if the result does not fit in cap bytes. */
int8_t cobs_decode(const uint8_t *src, uint16_t len, uint8_t *dst, uint16_t cap,
                   uint16_t *out_len);
#endif
