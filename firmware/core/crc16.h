/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0 (PROTOCOL.md).
 * Check value: crc16_ccitt("123456789") == 0x29B1. Bitwise, no table (no RAM, ~40 B flash). */
#ifndef SMA_CRC16_H
#define SMA_CRC16_H
#include <stdint.h>

#define CRC16_INIT 0xFFFFu

/* Feed one byte into a running CRC. */
uint16_t crc16_update(uint16_t crc, uint8_t byte);
/* CRC of a whole buffer, starting from CRC16_INIT. */
uint16_t crc16_ccitt(const uint8_t *data, uint8_t len);
#endif
