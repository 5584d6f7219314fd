"""A Python implementation of the current-driver firmware's behaviour (firmware/PROTOCOL.md).

Same commands, ACK status codes, telemetry and safety rules as the C core: output off at start,
after the host timeout, on a latched fault and on ENABLE 0; setpoints clamped to the active limit
(never above the 2500 mA hard limit); OVERCURRENT and OPEN_WIRE latch until CLEAR_FAULTS.
The frame codec is shared with the host driver (``smabench.drivers.protocol``).

The electrical side is a first-order current loop: the measured current follows the clamped
setpoint with the firmware's settling time, limited by what the supply can push through the
wire (``supply_v / (wire + shunt + switch resistance)``).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass

from smabench.drivers import protocol as p

log = logging.getLogger(__name__)

HARD_LIMIT_MA = 2500
FW_VERSION = (1, 0, 0)
DEVICE_NAME = b"SMA-CD328-MOCK"
CURRENT_TAU_MS = 8.0  # first-order settling: 5 % in ≈ 24 ms, inside the 50 ms spec
SERIES_OHM = 0.2  # shunt 0.1 Ω + switch and wiring 0.1 Ω
OPEN_WIRE_DUTY = 0.5
OPEN_WIRE_MA = 20
OPEN_WIRE_MS = 50
OVERCURRENT_FACTOR = 1.2
OVERCURRENT_MS = 5
MAX_DUTY = 0.95


@dataclass
class Electrical:
    """What the wire looks like to the driver right now."""

    resistance_ohm: float = 0.5
    supply_v: float = 5.0
    ambient_c: float = 22.0
    open_wire: bool = False


class MockFirmware:
    """Device state machine: feed it bytes from the host and time; it returns bytes to send."""

    def __init__(self, now_ms: float = 0.0) -> None:
        self.receiver = p.FrameReceiver()
        self.tx_seq = 0
        self.enabled = False
        self.setpoint_ma = 0
        self.limit_ma = HARD_LIMIT_MA
        self.host_timeout_ms = 250
        self.telemetry_period_ms = 0
        self.flags = 0
        self.current_ma = 0.0
        self.voltage_mv = 0.0
        self.duty = 0.0
        self.last_rx_ms = now_ms
        self.last_tick_ms = now_ms
        self.next_telemetry_ms = now_ms
        self._overcurrent_ms = 0.0
        self._open_ms = 0.0
        self.start_ms = now_ms

    # ------------------------------------------------------------------ frames
    def _frame(self, type_: int, payload: bytes) -> bytes:
        out = p.encode_frame(self.tx_seq, type_, payload)
        self.tx_seq = (self.tx_seq + 1) & 0xFF
        return out

    def _ack(self, seq: int, type_: int, status: int, data: bytes = b"") -> bytes:
        return self._frame(p.MsgType.ACK, bytes((seq, type_, status)) + data)

    def receive(self, data: bytes, now_ms: float) -> bytes:
        """Handle bytes from the host; returns the ACK frames to send back."""
        out = bytearray()
        for pkt in self.receiver.feed(data):
            self.last_rx_ms = now_ms
            out += self._handle(pkt.seq, pkt.type, pkt.payload)
        return bytes(out)

    def _handle(self, seq: int, type_: int, payload: bytes) -> bytes:
        S = p.Status
        expected = {
            p.MsgType.IDENTIFY: 1,
            p.MsgType.ENABLE: 1,
            p.MsgType.SET_CURRENT: 2,
            p.MsgType.SET_LIMITS: 4,
            p.MsgType.SET_TELEMETRY: 2,
            p.MsgType.CLEAR_FAULTS: 0,
            p.MsgType.PING: 0,
        }
        if type_ not in expected:
            return self._ack(seq, type_, S.UNKNOWN_COMMAND)
        if len(payload) != expected[type_]:
            return self._ack(seq, type_, S.BAD_LENGTH)
        if type_ == p.MsgType.IDENTIFY:
            info = bytes((p.PROTOCOL_VERSION, *FW_VERSION)) + struct.pack("<H", HARD_LIMIT_MA)
            status = S.OK if payload[0] == p.PROTOCOL_VERSION else S.VERSION_MISMATCH
            return self._ack(seq, type_, status, info + DEVICE_NAME)
        if type_ == p.MsgType.ENABLE:
            if payload[0] not in (0, 1):
                return self._ack(seq, type_, S.OUT_OF_RANGE)
            if payload[0] == 1:
                if self.flags & (p.Flag.OVERCURRENT | p.Flag.OPEN_WIRE):
                    return self._ack(seq, type_, S.FAULT_ACTIVE)
                self.flags &= ~p.Flag.HOST_TIMEOUT
                self.enabled = True
            else:
                self.enabled = False
            return self._ack(seq, type_, S.OK)
        if type_ == p.MsgType.SET_CURRENT:
            (ma,) = struct.unpack("<H", payload)
            if ma > self.limit_ma:
                self.setpoint_ma = self.limit_ma
                return self._ack(seq, type_, S.CLAMPED)
            self.setpoint_ma = ma
            return self._ack(seq, type_, S.OK)
        if type_ == p.MsgType.SET_LIMITS:
            limit, timeout = struct.unpack("<HH", payload)
            if limit > HARD_LIMIT_MA or not 20 <= timeout <= 5000:
                return self._ack(seq, type_, S.OUT_OF_RANGE)
            self.limit_ma, self.host_timeout_ms = limit, timeout
            self.setpoint_ma = min(self.setpoint_ma, limit)
            return self._ack(seq, type_, S.OK)
        if type_ == p.MsgType.SET_TELEMETRY:
            (period,) = struct.unpack("<H", payload)
            if period != 0 and not 5 <= period <= 1000:
                return self._ack(seq, type_, S.OUT_OF_RANGE)
            self.telemetry_period_ms = period
            return self._ack(seq, type_, S.OK)
        if type_ == p.MsgType.CLEAR_FAULTS:
            self.flags &= ~(
                p.Flag.OVERCURRENT | p.Flag.OPEN_WIRE | p.Flag.HOST_TIMEOUT | p.Flag.WATCHDOG_RESET
            )
            return self._ack(seq, type_, S.OK)
        return self._ack(seq, type_, S.OK)  # PING

    # ------------------------------------------------------------------ time
    def tick(self, now_ms: float, wire: Electrical) -> bytes:
        """Advance the device to ``now_ms``; returns telemetry frames that fell due."""
        dt_ms = max(0.0, now_ms - self.last_tick_ms)
        self.last_tick_ms = now_ms
        if self.enabled and now_ms - self.last_rx_ms > self.host_timeout_ms:
            log.info("host timeout after %.0f ms: output off", now_ms - self.last_rx_ms)
            self.enabled = False
            self.flags |= p.Flag.HOST_TIMEOUT
        total_ohm = wire.resistance_ohm + SERIES_OHM
        max_ma = MAX_DUTY * wire.supply_v / total_ohm * 1e3
        target_ma = min(self.setpoint_ma, self.limit_ma) if self.enabled else 0.0
        if wire.open_wire:
            max_ma = 0.0
        target = min(target_ma, max_ma)
        if dt_ms > 0:
            gain = 1.0 - math.exp(-dt_ms / CURRENT_TAU_MS)
            self.current_ma += (target - self.current_ma) * gain
        if not self.enabled:
            self.current_ma = 0.0 if dt_ms > 0 else self.current_ma
        self.duty = 0.0
        if self.enabled:
            self.duty = (
                MAX_DUTY
                if wire.open_wire
                else min(MAX_DUTY, self.current_ma * 1e-3 * total_ohm / wire.supply_v)
            )
        limit_active = (
            self.enabled and target_ma > 0 and (target_ma >= self.limit_ma or target_ma > max_ma)
        )
        self.flags = (
            (self.flags | p.Flag.LIMIT_ACTIVE)
            if limit_active
            else (self.flags & ~p.Flag.LIMIT_ACTIVE)
        )
        self.voltage_mv = self.current_ma * wire.resistance_ohm
        self._check_faults(dt_ms)
        if self.enabled:
            self.flags |= p.Flag.ENABLED
        else:
            self.flags &= ~p.Flag.ENABLED
        out = bytearray()
        if self.telemetry_period_ms and now_ms >= self.next_telemetry_ms:
            out += self._frame(p.MsgType.TELEMETRY, self.telemetry_payload(now_ms, wire.ambient_c))
            self.next_telemetry_ms = max(
                self.next_telemetry_ms + self.telemetry_period_ms, now_ms - self.telemetry_period_ms
            )
        return bytes(out)

    def _check_faults(self, dt_ms: float) -> None:
        if not self.enabled:
            self._overcurrent_ms = self._open_ms = 0.0
            return
        if self.current_ma > OVERCURRENT_FACTOR * self.limit_ma:
            self._overcurrent_ms += dt_ms
        else:
            self._overcurrent_ms = 0.0
        if self.duty > OPEN_WIRE_DUTY and self.current_ma < OPEN_WIRE_MA:
            self._open_ms += dt_ms
        else:
            self._open_ms = 0.0
        if self._overcurrent_ms >= OVERCURRENT_MS:
            self._latch(p.Flag.OVERCURRENT)
        if self._open_ms >= OPEN_WIRE_MS:
            self._latch(p.Flag.OPEN_WIRE)

    def _latch(self, flag: int) -> None:
        log.warning("fault latched: %s", p.Flag(flag).name)
        self.flags |= flag
        self.enabled = False
        self.current_ma = 0.0
        self.duty = 0.0

    def telemetry_payload(self, now_ms: float, ambient_c: float) -> bytes:
        return struct.pack(
            "<IHHHhHHHH",
            int(now_ms - self.start_ms) & 0xFFFFFFFF,
            int(round(max(0.0, self.current_ma))),
            min(0xFFFF, int(round(self.voltage_mv))),
            min(0xFFFF, int(round(self.duty * 0xFFFF))),
            int(round(ambient_c * 100)),
            int(self.flags) & 0xFFFF,
            int(self.setpoint_ma),
            min(0xFFFF, self.receiver.crc_errors),
            min(0xFFFF, self.receiver.frame_errors),
        )
