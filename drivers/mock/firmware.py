"""The current driver's firmware for the stand-ins: the REAL C core plus the electrical side.

Behaviour (commands, ACK codes, telemetry, lease, host timeout, latched faults, energy budget,
clamps, the current loop) is ``firmware/core/core.c`` itself, built for the host and loaded
through :mod:`.corelib`: one behaviour, one place to change. What is left here is what the
microcontroller's pins see, supplied through the host HAL every 1 ms control tick:

- the reference linear sink (:class:`smabench.hardware.LinearSink`) turns the core's PWM duty
  and enable line into the wire current (two RC poles, compliance; the enable line clamps the
  setpoint at once);
- the ADC readings: the fast-path current (ADC0), the wire supply through its divider (ADC1), the
  ambient NTC divider (ADC2); the ADS1115's wire-voltage and shunt codes; the MAX31855 word; the
  e-stop input level. The inputs besides the wire are fields of :class:`Electrical`.

:class:`MockFirmware` is driven by its owner: :meth:`~MockFirmware.receive` hands it the
host's bytes, :meth:`~MockFirmware.tick` advances it in device time; both return the bytes the
firmware queued for the host (its 128-byte TX ring, emptied by the transport at once).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from smabench.drivers import protocol as p
from smabench.drivers.mock.corelib import EEPROM_BYTES, Core
from smabench.drivers.mock.cut import FAULTS, HardwareCut
from smabench.hardware import ELECTRICAL, LinearSink

log = logging.getLogger(__name__)

TICK_MS = 1  # core_control_tick() period

_CS = ELECTRICAL["current_sense"]
_ADC_REF_V = float(_CS["adc_reference_v"])
_VREF_V = float(_CS["reference_v"])  # the REF3040 on A3
_LOOP_OHM = ELECTRICAL.loop_resistance_ohm  # supply, leads, fuse, clamps, eFuse, shunt
_SHUNT_OHM = ELECTRICAL.shunt_ohm
WDT_INTERRUPT_MS = 32  # the ATmega's own watchdog: interrupt (output off) after 32 ms ...
WDT_RESET_MS = 64  # ... reset 32 ms later (firmware/avr/hal_avr.c)
_ADC_FULL_Q4 = 1023 * 16
_SUPPLY_DIVIDER = float(ELECTRICAL["supply_monitor"]["divider"])
_NTC = ELECTRICAL["ntc"]
_WIRE_V_PER_LSB = ELECTRICAL.precise_wire_v_per_lsb
_SHUNT_A_PER_LSB = ELECTRICAL.precise_current_a_per_lsb
_CURRENT_A_PER_COUNT = ELECTRICAL.current_adc_a_per_count
_OPEN_OHM = 1e9
_TC_COLD_JUNCTION = (25 * 16) << 4  # MAX31855 internal temperature 25 °C (D15..D4)


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
    avcc_v: float = _ADC_REF_V  # the Nano's AVcc (USB through its diode: 4.65 … 5.0 V)
    wire_offset_v: float = 0.0  # the wire-voltage amplifier's offset, referred to the wire, V
    fault: str | None = None  # injected: "mosfet-short", "wire-to-ground", "mcu-hang"

    def __post_init__(self) -> None:
        if self.fault is not None and self.fault not in FAULTS:
            raise ValueError(f"unknown fault {self.fault!r}: one of {', '.join(FAULTS)}")


def _adc_q4(volts: float, avcc_v: float = _ADC_REF_V) -> int:
    """Mean ADC reading (1/16 counts) of an input at ``volts`` (10 bits, AVcc reference)."""
    return min(_ADC_FULL_Q4, max(0, round(volts / avcc_v * 1024.0 * 16.0)))


def _int16(x: float) -> int:
    return -32768 if x < -32768.0 else 32767 if x > 32767.0 else round(x)


def ntc_volts(wire: Electrical) -> float:
    """ADC2: the NTC divider (NTC on top, fixed resistor to ground); open: 0 V, shorted: AVcc."""
    if wire.ntc == "open":
        return 0.0
    if wire.ntc == "short":
        return _ADC_REF_V
    r = _NTC["r25_ohm"] * math.exp(_NTC["beta_k"] * (1.0 / (wire.ambient_c + 273.15) - 1 / 298.15))
    return _ADC_REF_V * _NTC["fixed_ohm"] / (r + _NTC["fixed_ohm"])


def max31855_word(wire: Electrical) -> int:
    """The MAX31855's 32-bit word: absent (all ones), a fault, or the temperature (0.25 °C)."""
    if wire.wire_temperature_c is None:
        return 0xFFFFFFFF
    if wire.thermocouple_fault:
        return 0x00010000 | (int(wire.thermocouple_fault) & 0x07) | _TC_COLD_JUNCTION
    q = round(wire.wire_temperature_c * 4.0) & 0x3FFF
    return (q << 18) | _TC_COLD_JUNCTION


class _Eeprom:
    """The EEPROM image of one firmware instance (indexable bytes; keeps the instance alive)."""

    def __init__(self, fw: MockFirmware) -> None:
        self._fw = fw

    def __len__(self) -> int:
        return EEPROM_BYTES

    def __getitem__(self, i):
        return self._fw._core.eeprom[i]

    def __setitem__(self, i: int, value: int) -> None:
        self._fw._core.eeprom[i] = value

    def __bytes__(self) -> bytes:
        return bytes(self._fw._core.eeprom)


class MockFirmware:
    """The C core with the reference sink and the device's inputs around it.

    ``now_ms``: device time at reset (ms); ``eeprom``: the EEPROM image of a previous instance
    (a reset keeps it; blank by default); ``watchdog_reset``: the reset cause was the watchdog."""

    def __init__(
        self,
        now_ms: float = 0.0,
        eeprom: bytes | bytearray | _Eeprom | None = None,
        watchdog_reset: bool = False,
    ) -> None:
        self._core = Core()
        if eeprom is not None:
            image = bytes(eeprom)
            if len(image) != EEPROM_BYTES:
                raise ValueError(f"EEPROM image of {len(image)} bytes, want {EEPROM_BYTES}")
            self._core.eeprom[:] = image
        self.sink = LinearSink()
        self.cut = HardwareCut()
        self.current_ma = 0.0  # the wire current now (device side), mA
        self.shunt_ma = 0.0  # through the shunt (the wire's, unless it is shorted to ground)
        self.fault_ms: float | None = None  # device time the injected fault began
        self.hang_ms = 0  # how long the main loop has been hung
        self.watchdog_resets = 0  # resets by the AVR's own watchdog after a hang
        self.start_ms = float(now_ms)  # device time of the reset
        self.core_ms = math.floor(now_ms)  # the core's hal_millis()
        self.last_tick_ms = float(now_ms)
        self._wire = Electrical()
        self._slow: tuple | None = None
        self._set_inputs(self._wire)
        self._core.init(watchdog_reset)

    # ------------------------------------------------------------------ state
    @property
    def state(self):
        """The core's own view (``core_state_t``): setpoint, limits, model temperature, …"""
        return self._core.state

    @property
    def enabled(self) -> bool:
        return bool(self._core.io.output_enabled)

    @property
    def flags(self) -> p.Flag:
        return p.Flag(self._core.state.flags)

    @property
    def setpoint_ma(self) -> int:
        return int(self._core.state.setpoint_ma)

    @property
    def last_rx_ms(self) -> int:
        """Device time of the last valid frame, ms (the host timeout runs from it)."""
        return int(self._core.state.last_rx_ms)

    @property
    def wire_model_c(self) -> float:
        return float(self._core.state.model_c)

    @property
    def eeprom(self) -> _Eeprom:
        return _Eeprom(self)

    def latch_fault(self, flag: p.Flag) -> None:
        """Fault injection: the core latches ``flag`` (a latched fault) now, output off."""
        if not flag & p.LATCHED_FAULTS:
            raise ValueError(f"{flag!r} is not a latched fault")
        self._core.latch_fault(int(flag))
        self._after_core()

    # ------------------------------------------------------------------ the UART
    def receive(self, data: bytes, now_ms: float | None = None) -> bytes:
        """Bytes from the host (``now_ms`` is informative: the core runs on its own ticks);
        returns what the firmware queued for the host (its ACKs)."""
        out = bytearray()
        view = memoryview(bytes(data))
        if self._wire.fault == "mcu-hang":  # a hung loop reads nothing: the bytes wait (a reset
            self._core.rx_push(bytes(view))  # loses them)
            return b""
        while view or self._core.rx_pending():
            pending = self._core.rx_pending()
            taken = self._core.rx_push(bytes(view)) if view else 0
            view = view[taken:]
            self._core.poll()  # reads while its longest ACK fits in the TX ring
            sent = self._core.tx_take()
            out += sent
            if not taken and not sent and self._core.rx_pending() == pending:
                break  # pragma: no cover - no progress: the core holds what it has
        self._after_core()
        return bytes(out)

    # ------------------------------------------------------------------ time
    def tick(self, now_ms: float, wire: Electrical | None = None) -> bytes:
        """Advance the device to ``now_ms`` (one core tick per whole ms, the sink in between);
        returns the frames it queued meanwhile (telemetry)."""
        if wire is not None:
            self._wire = wire
        out = bytearray()
        self.last_tick_ms = max(self.last_tick_ms, float(now_ms))
        while self.core_ms + TICK_MS <= now_ms + 1e-9:
            fault = self._wire.fault
            if fault is not None and self.fault_ms is None:
                self.fault_ms = float(self.core_ms)
            elif fault is None:
                self.fault_ms = None
            self._sink_step(TICK_MS / 1000.0)
            self.core_ms += TICK_MS
            self._set_inputs(self._wire)
            if fault == "mcu-hang":
                self._hung_tick()
                continue
            self.hang_ms = 0
            self._core.poll()
            self._core.control_tick()
            self._after_core()
            out += self._core.tx_take()
        return bytes(out)

    def _hung_tick(self) -> None:
        """The main loop is stuck: no poll, no control tick, no D7 edges. Only the AVR's own
        watchdog runs (interrupt: output off after 32 ms; reset after 64 ms, then the loop runs
        again: the hang was a stuck wait that the reset ends)."""
        self.hang_ms += TICK_MS
        io = self._core.io
        if self.hang_ms == WDT_INTERRUPT_MS:
            io.pwm_duty = 0
            io.output_enabled = 0
            self._after_core()
        if self.hang_ms >= WDT_RESET_MS:
            log.info("stand-in: the MCU's watchdog resets it after a %d ms hang", self.hang_ms)
            latch, feeds = io.cut_latch, io.cut_feeds
            self._core.init(True)
            io.cut_latch = latch  # the cut's hardware keeps its state through the MCU's reset
            io.cut_feeds = feeds
            self.watchdog_resets += 1
            self.hang_ms = 0

    @property
    def cut_closed(self) -> bool:
        """U10 conducts: the MCU enables (D8) and the latch is clear."""
        io = self._core.io
        return bool(io.output_enabled) and not io.cut_latch

    def _sink_step(self, dt_s: float) -> None:
        wire = self._wire
        io = self._core.io
        if wire.supply_v is not None:
            self.sink.supply_v = wire.supply_v
        self.cut.feed(io.cut_feeds)
        self.cut.decay(dt_s)
        r_wire = _OPEN_OHM if wire.open_wire else wire.resistance_ohm
        closed = self.cut_closed
        sink_a = supply_a = 0.0
        if closed:
            if wire.fault == "mosfet-short":  # the current no longer follows the setpoint
                sink_a = supply_a = self.sink.supply_v / (_LOOP_OHM + r_wire)
            elif wire.fault == "wire-to-ground":  # past the shunt: the sink sees nothing
                supply_a = self.sink.supply_v / (_LOOP_OHM - _SHUNT_OHM + r_wire)
            else:
                sink_a = supply_a = self.sink.step(io.pwm_duty, r_wire, dt_s)
        cause = self.cut.comparators(sink_a, supply_a, wire.estop)
        io.cut_hold = 1 if wire.estop or self.cut.pump_low else 0
        if cause is not None:
            # the comparators and the eFuse act within microseconds: the fault's current flows
            # for a negligible part of this millisecond
            self.cut.record(cause, float(self.core_ms), closed and not io.cut_latch)
            io.cut_latch = 1
            sink_a = supply_a = 0.0
        if not self.cut_closed:
            sink_a = supply_a = 0.0
            self.sink.state.pole1_a = self.sink.state.pole2_a = 0.0
        self.shunt_ma = sink_a * 1000.0
        self.current_ma = supply_a * 1000.0

    def _after_core(self) -> None:
        """The enable line clamps the sink's setpoint at once (the filter's poles too)."""
        if not self.cut_closed and (self.current_ma or self.sink.state.pole1_a):
            self.current_ma = self.shunt_ma = 0.0
            self.sink.state.pole1_a = self.sink.state.pole2_a = 0.0

    def _set_inputs(self, wire: Electrical) -> None:
        io = self._core.io
        i_a = self.current_ma / 1000.0
        avcc = wire.avcc_v
        io.millis = self.core_ms & 0xFFFFFFFF
        # ADC0: the shunt amplifier; the core adds half a count (a code k stands for [k, k+1))
        q4 = self.shunt_ma / 1000.0 / _CURRENT_A_PER_COUNT * 16.0 * (_ADC_REF_V / avcc) - 8.0
        io.adc_q4[0] = min(_ADC_FULL_Q4, max(0, round(q4)))
        supply_v = self.sink.supply_at_terminals_v(i_a)
        # A1: the switched supply, after U10 (0 V while the cut is open)
        io.adc_q4[1] = _adc_q4(supply_v * _SUPPLY_DIVIDER if self.cut_closed else 0.0, avcc)
        io.adc_q4[3] = max(0, _adc_q4(_VREF_V, avcc) - 8)  # the REF3040; a code k is [k, k+1)
        slow = (wire.ambient_c, wire.ntc, wire.wire_temperature_c, wire.thermocouple_fault,
                wire.avcc_v)
        if slow != self._slow:  # the NTC divider and the MAX31855 word change with these only
            self._slow = slow
            io.adc_q4[2] = _adc_q4(ntc_volts(wire) * wire.avcc_v / _ADC_REF_V, wire.avcc_v)
            io.tc_word = max31855_word(wire)
        io.estop = 1 if wire.estop else 0
        io.xadc_present = 1 if wire.vsense else 0
        wire_v = (supply_v if wire.open_wire else i_a * wire.resistance_ohm) + wire.wire_offset_v
        io.xadc_code[0] = _int16(wire_v / _WIRE_V_PER_LSB)
        io.xadc_code[1] = _int16(self.shunt_ma / 1000.0 / _SHUNT_A_PER_LSB)
        io.tc_bus_ok = 1

    # ------------------------------------------------------------------ telemetry
    def telemetry_payload(self, now_ms: float | None = None, wire: object = None) -> bytes:
        """The TELEMETRY payload of the present state (the core packs it)."""
        return self._core.telemetry_payload()

    def telemetry(self, now_ms: float | None = None, wire: object = None) -> p.Telemetry:
        """The device's state as a telemetry record (as the next frame would carry it)."""
        return p.Telemetry.from_payload(self._core.telemetry_payload())
