/* Constants of firmware/PROTOCOL.md shared by the core, the AVR build and the host tests. */
#ifndef SMA_PROTO_H
#define SMA_PROTO_H

/* Message types */
#define MSG_IDENTIFY 0x01u
#define MSG_ENABLE 0x02u
#define MSG_SET_CURRENT 0x03u
#define MSG_SET_LIMITS 0x04u
#define MSG_SET_TELEMETRY 0x05u
#define MSG_CLEAR_FAULTS 0x06u
#define MSG_PING 0x07u
#define MSG_ACK 0x80u
#define MSG_TELEMETRY 0x90u

/* ACK status codes */
#define ST_OK 0u
#define ST_UNKNOWN_COMMAND 1u
#define ST_BAD_LENGTH 2u
#define ST_OUT_OF_RANGE 3u
#define ST_FAULT_ACTIVE 4u
#define ST_VERSION_MISMATCH 5u
#define ST_CLAMPED 6u

/* Flags (u16) */
#define FLAG_ENABLED 0x0001u
#define FLAG_OVERCURRENT 0x0002u
#define FLAG_OPEN_WIRE 0x0004u
#define FLAG_HOST_TIMEOUT 0x0008u
#define FLAG_WATCHDOG_RESET 0x0010u
#define FLAG_LIMIT_ACTIVE 0x0020u
#define FLAGS_LATCHED (FLAG_OVERCURRENT | FLAG_OPEN_WIRE)

/* Device identity (IDENTIFY data) */
#define FW_VERSION_MAJOR 1u
#define FW_VERSION_MINOR 0u
#define FW_VERSION_PATCH 0u
#define DEVICE_NAME "SMA-CD328"

/* Ranges and safety thresholds */
#define HOST_TIMEOUT_DEFAULT_MS 250u
#define HOST_TIMEOUT_MIN_MS 20u
#define HOST_TIMEOUT_MAX_MS 5000u
#define TELEMETRY_MIN_MS 5u
#define TELEMETRY_MAX_MS 1000u
#define TELEMETRY_LEN 20u
#define OVERCURRENT_MS 5u    /* above limit * 1.2 for this long: latch */
#define OPEN_WIRE_MA 20u     /* below this ... */
#define OPEN_WIRE_MS 50u     /* ... at duty > 50 % for this long: latch */
#endif
