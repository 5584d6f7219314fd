/* Frame encoder and streaming receiver (see frame.h). */
#include "frame.h"
#include "crc16.h"

static void count(uint16_t *counter)
{
    if (*counter != 0xFFFFu) {
        (*counter)++;
    }
}

void frame_rx_init(frame_rx_t *rx)
{
    rx->len = 0;
    rx->overflow = 0;
    rx->crc_errors = 0;
    rx->frame_errors = 0;
}

/* Decode and check the buffered frame; 1 if it is a valid packet. */
static uint8_t rx_finish(frame_rx_t *rx, frame_packet_t *pkt)
{
    uint16_t n;
    if (cobs_decode(rx->buf, rx->len, rx->buf, sizeof rx->buf, &n) != 0 ||
        n < FRAME_MIN_PACKET || n > FRAME_MAX_PACKET) {
        count(&rx->frame_errors);
        return 0;
    }
    uint8_t body = (uint8_t)(n - 2u);
    uint16_t crc = (uint16_t)(rx->buf[body] | ((uint16_t)rx->buf[body + 1u] << 8));
    if (crc16_ccitt(rx->buf, body) != crc) {
        count(&rx->crc_errors);
        return 0;
    }
    pkt->seq = rx->buf[0];
    pkt->type = rx->buf[1];
    pkt->len = (uint8_t)(body - 2u);
    pkt->payload = &rx->buf[2];
    return 1;
}

uint8_t frame_rx_push(frame_rx_t *rx, uint8_t byte, frame_packet_t *pkt)
{
    if (byte != 0u) {
        if (rx->len < sizeof rx->buf) {
            rx->buf[rx->len++] = byte;
        } else {
            rx->overflow = 1; /* keep dropping until the next delimiter */
        }
        return 0;
    }
    uint8_t ok = 0;
    if (rx->overflow) {
        count(&rx->frame_errors);
    } else if (rx->len != 0u) {
        ok = rx_finish(rx, pkt);
    }
    rx->len = 0;
    rx->overflow = 0;
    return ok;
}

uint8_t frame_encode(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len,
                     uint8_t *out, uint8_t cap)
{
    if (len > FRAME_MAX_PAYLOAD || cap == 0u) {
        return 0;
    }
    cobs_enc_t e;
    uint16_t crc = crc16_update(crc16_update(CRC16_INIT, seq), type);
    cobs_enc_begin(&e, out, (uint16_t)(cap - 1u)); /* keep room for the delimiter */
    cobs_enc_put(&e, seq);
    cobs_enc_put(&e, type);
    for (uint8_t i = 0; i < len; i++) {
        crc = crc16_update(crc, payload[i]);
        cobs_enc_put(&e, payload[i]);
    }
    cobs_enc_put(&e, (uint8_t)(crc & 0xFFu));
    cobs_enc_put(&e, (uint8_t)(crc >> 8));
    uint16_t n = cobs_enc_end(&e);
    if (n == 0u) {
        return 0;
    }
    out[n] = 0u;
    return (uint8_t)(n + 1u);
}
