"""A Python implementation of the current-driver firmware's behaviour (firmware/PROTOCOL.md, v2).

Same commands, ACK status codes, telemetry and safety rules as the C core
(``firmware/core/core.c``): output off at start, after the host timeout, when the setpoint lease
expires (PINGs keep the link alive, only SET_CURRENT renews the lease), on a latched fault and on
ENABLE 0; setpoints clamped to the active limit (never above the 2500 mA hard limit);
OVERCURRENT, OPEN_WIRE, OVERTEMP (energy budget or thermocouple) and ESTOP latch until
CLEAR_FAULTS, which keeps a fault whose cause is still there (``FAULT_ACTIVE``); calibration and
the heat model live in an EEPROM image that survives a reset when it is handed to the next
instance. The frame codec is shared with the host driver (``smabench.drivers.protocol``).

The electrical side is the reference linear sink (:class:`smabench.hardware.LinearSink`): the
setpoint PWM through its two RC poles, limited by the supply's headroom (compliance) and by the
sink's dissipation limit. The device's inputs besides the wire (ambient NTC, thermocouple, e-stop,
external ADC) are fields of :class:`Electrical`.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass

from smabench.drivers import protocol as p
from smabench.hardware import ELECTRICAL, LinearSink

log = logging.getLogger(__name__)

F = p.Flag
S = p.Status
HARD_LIMIT_MA = 2500
FW_VERSION = (2, 0, 0)
DEVICE_NAME = b"SMA-CD328-MOCK"
OPEN_WIRE_SET_MA = 100
OPEN_WIRE_MA = 20
OPEN_WIRE_MS = 50
OVERCURRENT_FACTOR = 1.2
OVERCURRENT_MIN_MARGIN_MA = 50
OVERCURRENT_MS = 5
HEAT_REARM_K = 10.0
AMBIENT_FALLBACK_C = 40.0  # the energy budget's ambient while the NTC is faulty
NTC_RANGE_C = (-40.0, 125.0)  # the NTC's rated range: outside it a reading is implausible
SLOW_PERIOD_MS = 100.0  # NTC and thermocouple reads
DISSIPATION_MAX_W = float(ELECTRICAL["sink"]["dissipation_max_w"])
EE_CAL, EE_HEAT = 0, 16  # EEPROM block addresses, as firmware/core/core.h
TRIM_MAX = 0.125  # the current trim's range, relative (firmware/core/core.c TRIM_MAX_Q16)
NAN = float("nan")
EXPECTED_LEN = {
    p.MsgType.IDENTIFY: 1,
    p.MsgType.ENABLE: 1,
    p.MsgType.SET_CURRENT: 2,
    p.MsgType.SET_LIMITS: 4,
    p.MsgType.SET_TELEMETRY: 2,
    p.MsgType.CLEAR_FAULTS: 0,
    p.MsgType.PING: 0,
    p.MsgType.SET_LEASE: 2,
    p.MsgType.SET_CALIBRATION: 6,
    p.MsgType.GET_CALIBRATION: 0,
    p.MsgType.SET_HEAT_MODEL: 8,
    p.MsgType.GET_HEAT_MODEL: 0,
}


@dataclass
class Electrical:
    """What the driver sees right now: the wire and the device's other inputs.

    ``wire_temperature_c`` feeds the thermocouple (``None``: no MAX31855 fitted);
    ``thermocouple_fault`` is a :class:`~smabench.drivers.protocol.TcStatus` fault bit set;
    ``ntc`` is ``"ok"``, ``"open"`` or ``"short"``; ``estop`` is the e-stop input (True: tripped);
    ``vsense`` False: the external ADC does not answer."""

    resistance_ohm: float = 0.44
    supply_v: float | None = None  # None: the nominal wire supply (electrical.toml)
    ambient_c: float = 22.0
    open_wire: bool = False
    wire_temperature_c: float | None = None
    thermocouple_fault: int = 0
    ntc: str = "ok"
    estop: bool = False
    vsense: bool = True


def _crc(data: bytes) -> bytes:
    return struct.pack("<H", p.crc16_ccitt_false(data))


class MockFirmware:
    """Device state machine: feed it bytes from the host and time; it returns bytes to send.

    ``eeprom``: the EEPROM image of a previous instance (a reset keeps it); blank by default."""

    def __init__(self, now_ms: float = 0.0, eeprom: bytearray | None = None) -> None:
        self.receiver = p.FrameReceiver()
        self.eeprom = eeprom if eeprom is not None else bytearray(b"\xff" * 1024)
        self.tx_seq = 0
        self.enabled = False
        self.setpoint_ma = 0
        self.limit_ma = HARD_LIMIT_MA
        self.host_timeout_ms = int(p.HOST_TIMEOUT_DEFAULT_S * 1000)
        self.lease_ms = int(p.LEASE_DEFAULT_S * 1000)
        self.telemetry_period_ms = 0
        self.flags = F(0)
        self.current_ma = 0.0
        self.voltage_mv = 0.0
        self.duty = 0.0
        self.supply_v = float("nan")
        self.ambient_c = float("nan")
        self.thermocouple_c = float("nan")
        self.tc_status = p.TcStatus.ABSENT
        self.last_rx_ms = now_ms
        self.lease_start_ms = now_ms
        self.last_tick_ms = now_ms
        self.next_telemetry_ms = now_ms
        self.next_slow_ms = now_ms
        self._overcurrent_ms = 0.0
        self._open_ms = 0.0
        self._estop_seen = False
        self.start_ms = now_ms
        self.sink = LinearSink()
        self.calibration = p.Calibration()
        self.heat = p.HeatModel()
        self._load_eeprom()
        self._ambient_for_model = 22.0
        self.wire_model_c = self._ambient_for_model

    # ------------------------------------------------------------------ EEPROM
    def _block(self, addr: int, magic: int, size: int) -> bytes | None:
        raw = bytes(self.eeprom[addr : addr + size + 4])
        if raw[0] != magic or raw[1] != 1 or raw[-2:] != _crc(raw[:-2]):
            return None
        return raw[2:-2]

    def _store(self, addr: int, magic: int, data: bytes) -> None:
        body = bytes((magic, 1)) + data
        self.eeprom[addr : addr + len(body) + 2] = body + _crc(body)

    def _load_eeprom(self) -> None:
        ok = True
        data = self._block(EE_CAL, ord("C"), 6)
        try:
            self.calibration = p.Calibration.from_data(data) if data else p.Calibration()
            if data:
                self.calibration.to_data()  # range check
        except (ValueError, p.ProtocolError):
            data = None
        if data is None:
            self.calibration, ok = p.Calibration(), False
        data = self._block(EE_HEAT, ord("H"), 8)
        try:
            heat = p.HeatModel.from_data(data) if data else None
            if heat is not None:
                heat.to_data()
        except (ValueError, p.ProtocolError):
            heat = None
        self.heat = heat or p.HeatModel()
        ok = ok and heat is not None
        self._set(F.CAL_DEFAULT, not ok)

    # ------------------------------------------------------------------ frames
    def _set(self, flag: F, on: bool) -> None:
        self.flags = (self.flags | flag) if on else (self.flags & ~flag)

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
            out += self._ack(pkt.seq, pkt.type, *self._handle(pkt.type, pkt.payload, now_ms))
        return bytes(out)

    def _handle(self, type_: int, payload: bytes, now_ms: float) -> tuple[int, bytes]:
        M = p.MsgType
        if type_ not in EXPECTED_LEN:
            return S.UNKNOWN_COMMAND, b""
        if len(payload) != EXPECTED_LEN[M(type_)]:
            return S.BAD_LENGTH, b""
        if type_ == M.IDENTIFY:
            info = bytes((p.PROTOCOL_VERSION, *FW_VERSION)) + struct.pack("<H", HARD_LIMIT_MA)
            status = S.OK if payload[0] == p.PROTOCOL_VERSION else S.VERSION_MISMATCH
            return status, info + DEVICE_NAME
        if type_ == M.ENABLE:
            return self._enable(payload[0], now_ms), b""
        if type_ == M.SET_CURRENT:
            (ma,) = struct.unpack("<H", payload)
            self.lease_start_ms = now_ms  # every SET_CURRENT renews the lease
            if ma > self.limit_ma:
                self.setpoint_ma = self.limit_ma
                return S.CLAMPED, b""
            self.setpoint_ma = ma
            return S.OK, b""
        if type_ == M.SET_LIMITS:
            limit, timeout = struct.unpack("<HH", payload)
            if limit > HARD_LIMIT_MA or not 20 <= timeout <= 5000:
                return S.OUT_OF_RANGE, b""
            self.limit_ma, self.host_timeout_ms = limit, timeout
            self.setpoint_ma = min(self.setpoint_ma, limit)
            return S.OK, b""
        if type_ == M.SET_TELEMETRY:
            (period,) = struct.unpack("<H", payload)
            if period != 0 and not 5 <= period <= 1000:
                return S.OUT_OF_RANGE, b""
            self.telemetry_period_ms = period
            self.next_telemetry_ms = now_ms
            return S.OK, b""
        if type_ == M.SET_LEASE:
            (ms,) = struct.unpack("<H", payload)
            if not 20 <= ms <= 5000:
                return S.OUT_OF_RANGE, b""
            self.lease_ms = ms
            return S.OK, b""
        if type_ == M.CLEAR_FAULTS:
            return self._clear_faults(), b""
        if type_ == M.GET_CALIBRATION:
            return S.OK, self.calibration.to_data()
        if type_ == M.GET_HEAT_MODEL:
            return S.OK, self.heat.to_data()
        if type_ in (M.SET_CALIBRATION, M.SET_HEAT_MODEL):
            return self._store_settings(type_, payload), b""
        return S.OK, b""  # PING: feeds the host watchdog, never the lease

    def _enable(self, on: int, now_ms: float) -> int:
        if on not in (0, 1):
            return S.OUT_OF_RANGE
        if on == 0:
            self._off()
            return S.OK
        if self.flags & p.LATCHED_FAULTS:
            return S.FAULT_ACTIVE
        if not self.enabled:
            self._overcurrent_ms = self._open_ms = 0.0
        self.enabled = True
        self.lease_start_ms = now_ms
        self.flags &= ~(F.HOST_TIMEOUT | F.LEASE_EXPIRED)
        return S.OK

    def _clear_faults(self) -> int:
        keep = F(0)
        if self._estop_seen:
            keep |= F.ESTOP
        tmax = self.heat.max_temperature_c
        tc_hot = not math.isnan(self.thermocouple_c) and self.thermocouple_c >= tmax
        if self.flags & F.OVERTEMP and (self.wire_model_c > tmax - HEAT_REARM_K or tc_hot):
            keep |= F.OVERTEMP
        self.flags &= ~((p.LATCHED_FAULTS | p.EVENTS) & ~keep)
        self._overcurrent_ms = self._open_ms = 0.0
        return S.FAULT_ACTIVE if keep else S.OK

    def _store_settings(self, type_: int, payload: bytes) -> int:
        try:
            if type_ == p.MsgType.SET_CALIBRATION:
                value = p.Calibration.from_data(payload)
                value.to_data()
            else:
                value = p.HeatModel.from_data(payload)
                value.to_data()
        except (ValueError, p.ProtocolError):
            return S.OUT_OF_RANGE
        if self.enabled:
            return S.OUTPUT_ON
        if type_ == p.MsgType.SET_CALIBRATION:
            self._store(EE_CAL, ord("C"), payload)
        else:
            self._store(EE_HEAT, ord("H"), payload)
        self._load_eeprom()
        return S.OK

    # ------------------------------------------------------------------ time
    def _off(self) -> None:
        self.enabled = False
        self.duty = 0.0
        self.flags &= ~(F.ENABLED | F.LIMIT_ACTIVE | F.DISSIPATION)

    def _latch(self, flag: F) -> None:
        log.warning("fault latched: %s", flag.name)
        self.flags |= flag
        self._off()

    def _slow_inputs(self, wire: Electrical) -> None:
        """NTC plausibility and the thermocouple, as the firmware reads them every 100 ms."""
        lo, hi = NTC_RANGE_C
        if wire.ntc != "ok" or not lo <= wire.ambient_c <= hi:
            self.ambient_c = float("nan")
            self._ambient_for_model = AMBIENT_FALLBACK_C
        else:
            self.ambient_c = wire.ambient_c
            self._ambient_for_model = wire.ambient_c
        self._set(F.NTC_FAULT, math.isnan(self.ambient_c))
        if wire.wire_temperature_c is None:
            self.tc_status, self.thermocouple_c = p.TcStatus.ABSENT, float("nan")
        elif wire.thermocouple_fault:
            self.tc_status = p.TcStatus(wire.thermocouple_fault & 0x07)
            self.thermocouple_c = float("nan")
        else:
            self.tc_status = p.TcStatus(0)
            self.thermocouple_c = round(wire.wire_temperature_c * 4.0) / 4.0  # 0.25 °C
        self._set(F.TC_FAULT, bool(self.tc_status & 0x07))

    def tick(self, now_ms: float, wire: Electrical) -> bytes:
        """Advance the device to ``now_ms``; returns telemetry frames that fell due."""
        dt_ms = max(0.0, now_ms - self.last_tick_ms)
        self.last_tick_ms = now_ms
        if wire.supply_v is not None:
            self.sink.supply_v = wire.supply_v
        if now_ms >= self.next_slow_ms:
            self._slow_inputs(wire)
            self.next_slow_ms = now_ms + SLOW_PERIOD_MS
        self._set(F.VSENSE_FAULT, not wire.vsense)
        self._estop_seen = wire.estop
        if wire.estop and not self.flags & F.ESTOP:
            self._latch(F.ESTOP)
        if self.enabled and now_ms - self.last_rx_ms >= self.host_timeout_ms:
            log.info("host timeout after %.0f ms: output off", now_ms - self.last_rx_ms)
            self._off()
            self.flags |= F.HOST_TIMEOUT
        if self.enabled and self.setpoint_ma and now_ms - self.lease_start_ms >= self.lease_ms:
            log.info("setpoint lease expired after %.0f ms: output off", self.lease_ms)
            self._off()
            self.setpoint_ma = 0
            self.flags |= F.LEASE_EXPIRED
        sp_ma = min(self.setpoint_ma, self.limit_ma)
        # the sink's dissipation limit (firmware: a current cap from the measured voltages)
        cap_ma = math.inf
        v_fet = self.sink.supply_at_terminals_v(self.current_ma / 1e3) - self.voltage_mv / 1e3 - (
            self.current_ma / 1e3 * ELECTRICAL.shunt_ohm)  # fmt: skip
        if v_fet > 0:
            cap_ma = DISSIPATION_MAX_W / v_fet * 1e3
        dissipating = self.enabled and sp_ma > cap_ma
        if dissipating:
            sp_ma = cap_ma
        phys_ma = self._trimmed_ma(sp_ma)  # the trim regulates the calibrated measurement
        counts = phys_ma / 1000.0 / ELECTRICAL.setpoint_a_per_count if self.enabled else 0.0
        if dt_ms > 0:
            r_wire = 1e9 if wire.open_wire else wire.resistance_ohm
            current_a = self.sink.step(counts, r_wire, dt_ms / 1000.0)
            self.current_ma = current_a * 1000.0 if self.enabled else 0.0
            if not self.enabled:  # the enable line clamps the setpoint at once
                self.sink.state.pole1_a = self.sink.state.pole2_a = 0.0
        self.duty = min(1.0, counts / ELECTRICAL["setpoint"]["pwm_top"]) if self.enabled else 0.0
        self.voltage_mv = (
            self.sink.supply_at_terminals_v(0.0) * 1e3
            if wire.open_wire
            else self.current_ma * wire.resistance_ohm
        )
        self.supply_v = self.sink.supply_at_terminals_v(self.current_ma / 1e3)
        compliance = not wire.open_wire and sp_ma > 1000.0 * self.sink.compliance_a(
            wire.resistance_ohm)  # fmt: skip
        self._set(
            F.LIMIT_ACTIVE,
            self.enabled and sp_ma > 0 and (sp_ma >= self.limit_ma or compliance or dissipating),
        )
        self._set(F.DISSIPATION, dissipating)
        self._heat(dt_ms)
        self._check_faults(dt_ms, sp_ma)
        self._set(F.ENABLED, self.enabled)
        out = bytearray()
        if self.telemetry_period_ms and now_ms >= self.next_telemetry_ms:
            out += self._frame(p.MsgType.TELEMETRY, self.telemetry_payload(now_ms, wire))
            self.next_telemetry_ms = max(
                self.next_telemetry_ms + self.telemetry_period_ms, now_ms - self.telemetry_period_ms
            )
        return bytes(out)

    def _trimmed_ma(self, sp_ma: float) -> float:
        """The wire current, mA, whose calibrated measurement is ``sp_ma``: the firmware's trim
        (a settled one) regulates ``(I − offset)·gain`` to the setpoint, within ±12.5 %."""
        cal = self.calibration
        want = sp_ma / cal.current_gain + cal.current_offset_a * 1e3
        return min(max(want, sp_ma * (1.0 - TRIM_MAX)), sp_ma * (1.0 + TRIM_MAX))

    def _measured_ma(self) -> float:
        """The fast-path current as the firmware reports it (calibrated), mA."""
        cal = self.calibration
        return max(0.0, self.current_ma - cal.current_offset_a * 1e3) * cal.current_gain

    def _heat(self, dt_ms: float) -> None:
        """The energy budget: the same heat model as the firmware, conservative by its
        parameters; latches OVERTEMP at the maximum (or when the thermocouple reads it)."""
        i_a = self.current_ma / 1000.0
        if self.enabled:
            i_a = max(i_a, self.setpoint_ma / 1000.0)
        h = self.heat
        r = h.resistance_ohm
        if self.current_ma > 50 and not self.flags & F.VSENSE_FAULT:
            r = max(r, self.voltage_mv / self.current_ma)
        steps = max(1, round(dt_ms))
        dt_s = dt_ms / 1000.0 / steps
        for _ in range(steps):
            loss_w = h.conductance_w_per_k * (self.wire_model_c - self._ambient_for_model)
            self.wire_model_c += (i_a * i_a * r - loss_w) * dt_s / h.heat_capacity_j_per_k
        tc_hot = not math.isnan(self.thermocouple_c) and self.thermocouple_c >= h.max_temperature_c
        if (self.wire_model_c >= h.max_temperature_c or tc_hot) and not self.flags & F.OVERTEMP:
            self._latch(F.OVERTEMP)

    def _check_faults(self, dt_ms: float, sp_ma: float) -> None:
        if not self.enabled:
            self._overcurrent_ms = self._open_ms = 0.0
            return
        limit = self.limit_ma
        threshold = max(OVERCURRENT_FACTOR * limit, limit + OVERCURRENT_MIN_MARGIN_MA)
        self._overcurrent_ms = self._overcurrent_ms + dt_ms if self.current_ma > threshold else 0.0
        if sp_ma >= OPEN_WIRE_SET_MA and self.current_ma < OPEN_WIRE_MA:
            self._open_ms += dt_ms
        else:
            self._open_ms = 0.0
        if self._overcurrent_ms >= OVERCURRENT_MS:
            self._latch(F.OVERCURRENT)
            self.current_ma = 0.0
        elif self._open_ms >= OPEN_WIRE_MS:
            self._latch(F.OPEN_WIRE)
            self.current_ma = 0.0

    def telemetry(self, now_ms: float, wire: Electrical) -> p.Telemetry:
        """The device's state as a telemetry record."""
        vsense = wire.vsense
        return p.Telemetry(
            t_ms=int(now_ms - self.start_ms) & 0xFFFFFFFF,
            current_a=self._measured_ma() / 1000.0,
            voltage_v=self.voltage_mv * self.calibration.voltage_gain / 1e3 if vsense else NAN,
            duty=self.duty,
            ambient_c=self.ambient_c,
            flags=F(int(self.flags) & 0xFFFF),
            setpoint_a=self.setpoint_ma / 1000.0,
            crc_errors=min(0xFFFF, self.receiver.crc_errors),
            frame_errors=min(0xFFFF, self.receiver.frame_errors),
            wire_model_c=self.wire_model_c,
            thermocouple_c=self.thermocouple_c,
            precise_current_a=max(0.0, self.current_ma) * self.calibration.current_gain / 1e3
            if vsense
            else NAN,
            supply_v=self.supply_v,
            thermocouple_status=self.tc_status,
        )

    def telemetry_payload(self, now_ms: float, wire: Electrical | float) -> bytes:
        """TELEMETRY payload; ``wire`` may be a bare ambient (°C) as in protocol v1's model."""
        if not isinstance(wire, Electrical):
            wire = Electrical(ambient_c=float(wire))
        return self.telemetry(now_ms, wire).to_payload()
