/* Frames of PROTOCOL.md: COBS(seq, type, payload[0..60], CRC16 LE) + 0x00 delimiter. */
#ifndef SMA_FRAME_H
#define SMA_FRAME_H
#include <stdint.h>
#include "cobs.h"

#define FRAME_MAX_PAYLOAD 60u
#define FRAME_MIN_PACKET 4u                            /* seq, type, CRC */
#define FRAME_MAX_PACKET (FRAME_MAX_PAYLOAD + 4u)      /* 64 */
#define FRAME_MAX_ENCODED COBS_MAX_ENCODED(FRAME_MAX_PACKET) /* 65, without delimiter */
#define FRAME_MAX_WIRE (FRAME_MAX_ENCODED + 1u)        /* 66, with the 0x00 delimiter */

/* A decoded packet. payload points into the receiver buffer: valid until the next push. */
typedef struct {
    uint8_t seq;
    uint8_t type;
    uint8_t len; /* payload bytes, 0 ... FRAME_MAX_PAYLOAD */
    const uint8_t *payload;
} frame_packet_t;

/* Streaming receiver: buffers encoded bytes until 0x00, decodes in place. 70 bytes of RAM. */
typedef struct {
    uint8_t buf[FRAME_MAX_ENCODED];
    uint8_t len;           /* encoded bytes buffered since the last delimiter */
    uint8_t overflow;      /* frame too long: dropping bytes until the next 0x00 */
    uint16_t crc_errors;   /* saturating */
    uint16_t frame_errors; /* saturating: bad COBS, too short, too long */
} frame_rx_t;

void frame_rx_init(frame_rx_t *rx);
/* Push one received byte. Returns 1 when it completed a valid packet (written to *pkt),
 * else 0. Empty frames (two delimiters in a row) are ignored without counting. */
uint8_t frame_rx_push(frame_rx_t *rx, uint8_t byte, frame_packet_t *pkt);

/* Encode a packet with delimiter into out; returns the bytes written (<= FRAME_MAX_WIRE), or 0
 * if len > FRAME_MAX_PAYLOAD or out is too small. */
uint8_t frame_encode(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len,
                     uint8_t *out, uint8_t cap);
#endif
