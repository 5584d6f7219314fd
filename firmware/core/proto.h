/* Constants of firmware/PROTOCOL.md (protocol version 4) shared by the core, the AVR build and
 * the host tests. drivers/protocol.py holds the same numbers for the host. */
#ifndef SMA_PROTO_H
#define SMA_PROTO_H

#define PROTOCOL_VERSION 4u /* 4: SET_PROBE (the probe current) */

/* Message types */
#define MSG_IDENTIFY 0x01u
#define MSG_ENABLE 0x02u
#define MSG_SET_CURRENT 0x03u
#define MSG_SET_LIMITS 0x04u
#define MSG_SET_TELEMETRY 0x05u
#define MSG_CLEAR_FAULTS 0x06u
#define MSG_PING 0x07u
#define MSG_SET_LEASE 0x08u
#define MSG_SET_CALIBRATION 0x09u
#define MSG_GET_CALIBRATION 0x0Au
#define MSG_SET_HEAT_MODEL 0x0Bu
#define MSG_GET_HEAT_MODEL 0x0Cu
#define MSG_SET_PROBE 0x0Du /* protocol version 4 */
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
#define ST_OUTPUT_ON 7u /* refused while the output is enabled (EEPROM writes) */

/* Flags (u16) */
#define FLAG_ENABLED 0x0001u
#define FLAG_OVERCURRENT 0x0002u   /* latched */
#define FLAG_OPEN_WIRE 0x0004u     /* latched */
#define FLAG_HOST_TIMEOUT 0x0008u  /* event */
#define FLAG_WATCHDOG_RESET 0x0010u /* event */
#define FLAG_LIMIT_ACTIVE 0x0020u  /* state */
#define FLAG_LEASE_EXPIRED 0x0040u /* event */
#define FLAG_OVERTEMP 0x0080u      /* latched: energy budget or thermocouple above the maximum */
#define FLAG_ESTOP 0x0100u         /* latched: hardware e-stop input */
#define FLAG_NTC_FAULT 0x0200u     /* state: ambient NTC open or shorted */
#define FLAG_TC_FAULT 0x0400u      /* state: thermocouple chip reports OC/SCG/SCV */
#define FLAG_VSENSE_FAULT 0x0800u  /* state: external ADC (wire voltage) not answering */
#define FLAG_CAL_DEFAULT 0x1000u   /* state: EEPROM calibration invalid, defaults in use */
#define FLAG_DISSIPATION 0x2000u   /* state: current reduced to keep the sink's dissipation */
#define FLAG_CUT_TRIP 0x4000u      /* latched: the hardware cut opened unasked (its latch U8 set by a
                                      comparator, the external watchdog or the e-stop; or the
                                      switch or switched supply gone while enabled) */
#define FLAG_CUT_OPEN 0x8000u      /* state: the series switch U10 is open (D5 reads EN low) */
#define FLAGS_LATCHED (FLAG_OVERCURRENT | FLAG_OPEN_WIRE | FLAG_OVERTEMP | FLAG_ESTOP | FLAG_CUT_TRIP)
#define FLAGS_EVENTS (FLAG_HOST_TIMEOUT | FLAG_WATCHDOG_RESET | FLAG_LEASE_EXPIRED)

/* Thermocouple status byte (telemetry offset 28) */
#define TC_OC 0x01u     /* MAX31855 D0: open circuit */
#define TC_SCG 0x02u    /* D1: short to GND */
#define TC_SCV 0x04u    /* D2: short to VCC */
#define TC_ABSENT 0x80u /* no chip answered (reserved bits set, or all zeros) */

/* Telemetry sentinels */
#define TEMP_NONE 0x7FFF  /* i16 temperatures: not available / fault */
#define U16_NONE 0xFFFFu  /* u16 measurements: not available */

/* Device identity (IDENTIFY data) */
#define FW_VERSION_MAJOR 4u
#define FW_VERSION_MINOR 0u
#define FW_VERSION_PATCH 0u
#ifndef DEVICE_NAME /* the host library for the Python stand-ins says SMA-CD328-MOCK */
#define DEVICE_NAME "SMA-CD328"
#endif

/* Ranges and safety thresholds */
#define HARD_LIMIT_MA 2500u
#define HOST_TIMEOUT_DEFAULT_MS 250u
#define HOST_TIMEOUT_MIN_MS 20u
#define HOST_TIMEOUT_MAX_MS 5000u
#define LEASE_DEFAULT_MS 250u
#define LEASE_MIN_MS 20u
#define LEASE_MAX_MS 5000u
#define TELEMETRY_MIN_MS 5u
#define TELEMETRY_MAX_MS 1000u
#define TELEMETRY_LEN 29u
#define PROBE_MAX_MA 100u   /* SET_PROBE: 0 (off, the reset state) ... this; not stored */
#define PROBE_MAX_MW 20u   /* SET_PROBE: the probe held within this power on the heat model's R (a
                             * thin 20-ohm wire: 31 mA), so an unleased probe never heats */
#define OVERCURRENT_MS 5u    /* above limit * 1.2 for this long: latch */
#define OPEN_WIRE_SET_MA 100u /* setpoint at least this ... */
#define OPEN_WIRE_MA 20u     /* ... and measured below this ... */
#define OPEN_WIRE_MS 50u     /* ... for this long: latch */
#define CUT_STARTUP_MS 5u    /* after reset: D7 toggles this long (the pump charges), then D4 */
#define CUT_SUPPLY_MIN_MV 1000u /* switched supply (A1) below this while enabled ... */
#define CUT_SUPPLY_MS 5u     /* ... for this long (U10's soft start is ~1 ms): the cut opened */
#define AVCC_MIN_MV 4000u    /* AVcc measured on A3 outside this range: implausible, nominal used */
#define AVCC_MAX_MV 5600u

/* Calibration (SET_CALIBRATION): gains in Q15 (32768 = 1.0), 0.5 ... 1.5 */
#define CAL_GAIN_ONE 32768u
#define CAL_GAIN_MIN 16384u
#define CAL_GAIN_MAX 49152u
#define CAL_OFFSET_MAX_UA 32767
#define CAL_LEN 8u /* SET_CALIBRATION payload: i16 current offset uA, u16 current gain Q15,
                    * u16 voltage gain Q15, i16 wire-voltage offset uV (protocol version 3) */

/* Heat model (SET_HEAT_MODEL) ranges, in the wire units */
#define HEAT_R_MIN_MOHM 50u      /* resistance, mOhm */
#define HEAT_R_MAX_MOHM 20000u
#define HEAT_C_MIN 1u            /* heat capacity, 0.1 mJ/K */
#define HEAT_G_MIN 1u            /* heat loss conductance, 0.01 mW/K */
#define HEAT_TMAX_MIN_DC 300u    /* maximum temperature, 0.1 degC: 30 ... 400 degC */
#define HEAT_TMAX_MAX_DC 4000u
#endif
