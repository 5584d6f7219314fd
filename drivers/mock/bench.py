"""The mock bench: the plant simulation served over the real transports.

- current driver: :class:`~.serial_device.SerialDevice` (the Python firmware model,
  sharing the codec and the safety rules) on a pty, or with ``firmware="emulated"`` the real AVR
  firmware in simavr (``firmware/build/sim/smabench-sim``), coupled to the plant through the
  harness's stdin commands;
- displacement sensor: a pymodbus server with the shipped register map, on TCP (127.0.0.1) and,
  when socat is installed, on RTU over a socat pty pair.

The plant (:class:`~smabench.drivers.mock.plant_link.PlantLink`) is stepped by the current driver's
device time with the current it measures, so ``speed`` > 1 runs the whole bench faster. The
Modbus server reads the slider position from the plant at every request.

:meth:`MockBench.stop` ends everything the bench started (threads, harness, socat).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import math
import os
import queue
import re
import secrets
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from smabench.drivers.mock.cut import FAULTS
from smabench.drivers.mock.firmware import Electrical, MockFirmware
from smabench.drivers.mock.plant_link import PlantLink
from smabench.drivers.mock.serial_device import SerialDevice
from smabench.drivers.modbus_sim import SensorServer
from smabench.physics.effects import Effects
from smabench.physics.resistance import ResistivityModel
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SIM_BIN = Path(os.environ.get("SMABENCH_SIM", REPO / "firmware/build/sim/smabench-sim"))
SIM_ELF = Path(os.environ.get("SMABENCH_ELF", REPO / "firmware/build/avr/smabench-cd.elf"))
# the Arduino bootloader the emulator boots with --bootloader (`make -C firmware optiboot`)
BOOTLOADER_HEX = Path(
    os.environ.get("SMABENCH_BOOTLOADER", REPO / "firmware/build/boot/optiboot_atmega328.hex")
)
SENSOR_MAP = "generic-rs485-laser"
FIRMWARES = ("python", "emulated")
PR_SET_PDEATHSIG = 1
FAULT_ARM_MA = 500.0
"""An injected fault waits for the wire current to exceed this (mA): the cut has work to do."""
REALTIME_MAX_SPEED = 5.0
"""Fastest mock speed (device time / wall time) still run real-time with ``realtime``: at 5× a
mock's device thread takes 48 % of a core and its Modbus server 20 % (measured at fb7eda0; the
device thread took 79 % before it batched its steps), so two 5× sessions with their runs' loops
can exceed the kernel's real-time budget on two cores (open); faster ones take more."""


DEVICE_RT_PRIORITY = 10
"""SCHED_FIFO priority of the Python firmware's thread with ``realtime``, where allowed: below
the host's loop and link thread (20). It sleeps between frames and ticks, as a real-time thread
must."""
HARNESS_NICE = -10
"""Nice value of the simavr harness with ``realtime``, where allowed: CPU-favoured, but NOT
SCHED_FIFO. The harness takes about 85 % of a core to keep real time, and all of one while it
catches up; at SCHED_FIFO it starved whatever normal task shared its core: the kernel's worker
carrying the host's bytes through the pty, a host thread holding the interpreter lock the
control loop waits for. Beside a second harness and a CPU-bound process on 2 cores, 5 of 6
sessions failed so (the firmware's host timeout, the sensor lost, the loop stalled 0.5 s); at
nice -10, 6 of 6 passed, also beside two CPU-bound processes."""


def die_with_parent() -> None:
    """preexec_fn: the child gets SIGTERM when the mock process dies, even by SIGKILL (Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def realtime_child() -> None:
    """preexec_fn for a stand-in device process (the simavr harness): :func:`die_with_parent`,
    and nice :data:`HARNESS_NICE` where allowed (else unchanged)."""
    die_with_parent()
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, HARNESS_NICE)


@dataclass(frozen=True)
class MockPorts:
    """Where the clients connect: the driver's pty and the sensor's transport specs."""

    driver: str
    sensor_tcp: str
    sensor_rtu: str | None

    def lines(self) -> list[str]:
        out = [f"driver: {self.driver}", f"sensor-tcp: {self.sensor_tcp}"]
        if self.sensor_rtu:
            out.append(f"sensor-rtu: {self.sensor_rtu}")
        return out


class EmulatedDriver:
    """The real firmware in the simavr harness, coupled to the plant every ``couple_s``.

    A thread asks the harness for its state (``Q``), steps the plant with the measured current
    over the AVR time that passed, and sets the wire resistance and ambient (``R``, ``A``).
    """

    def __init__(
        self,
        link: PlantLink,
        couple_s: float = 0.002,
        bootloader: bool = False,
        blank: bool = False,
        thermocouple: bool = False,
        realtime: bool = False,
        fault: str | None = None,
        wire_noise_v: float = 0.0,
    ) -> None:
        """``wire_noise_v``: Gaussian noise of the emulated ADS1115's wire channel, V RMS at the
        wire, one draw per conversion (the harness's ``VNOISE``); ``realtime``: the harness at
        nice :data:`HARNESS_NICE` where allowed (it
        stands in for a microcontroller: starved by host load, it would fall silent while the
        host's link and telemetry timeouts run on); ``bootloader``: boot the Arduino
        bootloader (:data:`BOOTLOADER_HEX`) with the auto-reset of a Nano (every open of the
        port resets it); ``blank``: no application in the flash;
        ``thermocouple``: the emulated MAX31855 reads the plant's wire temperature (else none
        is fitted)."""
        self.thermocouple = thermocouple
        needed = [SIM_BIN] + ([BOOTLOADER_HEX] if bootloader else []) + ([] if blank else [SIM_ELF])
        for path in needed:
            if not path.is_file():
                raise FileNotFoundError(
                    f"{path} missing: build the firmware with `make -C firmware elf sim` in a "
                    "smabench checkout (the bootloader needs `apt-get install arduino-core-avr`; "
                    "or point SMABENCH_SIM, SMABENCH_ELF, SMABENCH_BOOTLOADER at the builds)"
                )
        self.link = link
        self.couple_s = couple_s
        self.fault = fault  # injected through the harness's FAULT command (MockBench's fault)
        self._fault_state = "armed" if fault else "none"
        boot = ["--bootloader", str(BOOTLOADER_HEX)] if bootloader else []
        self.proc = subprocess.Popen(
            [str(SIM_BIN), *boot, "--blank" if blank else str(SIM_ELF)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            bufsize=1,
            preexec_fn=realtime_child if realtime else die_with_parent,
        )
        first = self.proc.stdout.readline().strip()
        if not first.startswith("PTY "):
            self.stop()
            raise RuntimeError(f"simavr harness did not start: {first!r}")
        self.port_name = first[4:]
        if wire_noise_v > 0.0:
            self._send(f"VNOISE {wire_noise_v:.9g}")
        self._states: queue.Queue[str] = queue.Queue()
        self._running = True
        self._reader = threading.Thread(target=self._read, name="sim-reader", daemon=True)
        self._reader.start()
        self._coupler = threading.Thread(target=self._couple, name="sim-coupler", daemon=True)
        self._coupler.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if line.startswith("STATE"):
                self._states.put(line)

    def _send(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    _HARNESS_FAULT = {"mosfet-short": "MOSFET", "wire-to-ground": "GROUND", "mcu-hang": "HANG"}
    _CAUSES = {1: "sink-comparator", 2: "supply-comparator", 3: "estop", 4: "watchdog"}

    def _fault_step(self, line: str, current_a: float) -> None:
        """Inject the fault once the current flows; report the cut from the harness's STATE (its
        fault_ms, trip_ms, off_ms: AVR time)."""
        f = {k: float(v) for k, _, v in (tok.partition("=") for tok in line.split()[1:])}
        if self._fault_state == "armed" and current_a * 1000.0 >= FAULT_ARM_MA:
            self._send(f"FAULT {self._HARNESS_FAULT[self.fault]}")
            self._fault_state = "injected"
            self._injected_at_a = current_a  # the current it met (the next STATE is after it)
        elif self._fault_state == "injected" and f.get("fault_ms", -1) >= 0:
            print(f"fault: {self.fault} at {f['fault_ms']:.1f} ms (AVR time), wire current "
                  f"{self._injected_at_a * 1000:.0f} mA", flush=True)
            self._fault_state = "waiting"
        elif self._fault_state == "waiting" and f.get("off_ms", -1) >= 0:
            cause = self._CAUSES.get(int(f["cut_cause"]), "power-on")
            print(f"cut: opened by the {cause} {f['off_ms'] - f['fault_ms']:.2f} ms after the "
                  f"{self.fault} (AVR time); wire current now {current_a * 1000:.0f} mA",
                  flush=True)
            self._fault_state = "reported" if self.fault == "mcu-hang" else "done"
        elif self._fault_state == "reported" and f.get("fault", 0) == 0:
            print(f"mcu: reset by its own watchdog at {f['t_ms']:.0f} ms (AVR time)", flush=True)
            self._fault_state = "done"

    def _couple(self) -> None:
        last_ms: float | None = None
        pattern = re.compile(r"t_ms=(\S+) duty=(\S+) current_a=(\S+)")
        while self._running and self.proc.poll() is None:
            try:
                self._send("Q")
                m = pattern.search(self._states.get(timeout=1.0))
            except (queue.Empty, OSError, ValueError):
                continue
            if not m:
                continue
            t_ms, current_a = float(m.group(1)), float(m.group(3))
            if self.fault is not None:
                self._fault_step(m.string, current_a)
            if last_ms is not None and t_ms > last_ms:
                state = self.link.step((t_ms - last_ms) / 1000.0, current_a)
                with contextlib.suppress(OSError, ValueError):
                    self._send(f"R {state.resistance_ohm:.5f}")
                    self._send(f"A {state.ambient_c:.2f}")
                    if self.thermocouple:
                        self._send(f"TC {state.temperature_c:.2f}")
            last_ms = t_ms
            time.sleep(self.couple_s)

    def stop(self) -> None:
        self._running = False
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.close()  # EOF on stdin ends the harness
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class MockBench:
    """Plant + current driver + displacement sensor, served over real transports."""

    def __init__(
        self,
        load_kg: float = 2.0,
        *,
        speed: float = 1.0,
        effects: Effects | None = None,
        firmware: str = "python",
        wire: Wire = PAPER_WIRE,
        tcp_port: int = 0,
        rtu: bool = True,
        noise_mm: float = 0.002,
        seed: int = 0,
        trace: str | Path | None = None,
        bootloader: bool = False,
        blank: bool = False,
        sensor_map: str = SENSOR_MAP,
        adapter_latency_s: float = 0.0,
        thermocouple: bool = False,
        realtime: bool = False,
        fault: str | None = None,
        resistivity: ResistivityModel | None = None,
        wire_noise_v: float = 0.0,
    ) -> None:
        """``realtime``: at real-time speed (1), the stand-in driver favoured where allowed (the
        Python firmware's thread SCHED_FIFO :data:`DEVICE_RT_PRIORITY`, the simavr harness at
        nice :data:`HARNESS_NICE`);
        ``trace``: a CSV path for what the plant really got (:class:`PlantTrace`);
        ``bootloader``, ``blank``: see :class:`EmulatedDriver` (emulated firmware only);
        ``sensor_map``: the register map the sensor serves (any shipped map or a path);
        ``adapter_latency_s``: every sensor answer held this long, as by an FTDI USB/RS-485
        adapter's latency timer (16 ms by default on a real one); ``thermocouple``: a MAX31855 on
        the wire reports the plant's wire temperature (the session's ``temperature_C``);
        ``fault``: one of :data:`~smabench.drivers.mock.cut.FAULTS`, injected once the wire
        current first exceeds :data:`FAULT_ARM_MA` (the emulated firmware: through the
        harness's FAULT command, timed by the harness): a shorted MOSFET or a wire
        shorted to ground stays; a hung MCU ends with its own watchdog's reset. What the hardware
        cut did is printed on stdout and kept in :attr:`fault_report`; ``resistivity``: the
        wire's resistance from that model (:mod:`smabench.physics.resistance`: R(ξ, T, ε), so
        the wire voltage the driver measures is I·R(ξ, T, ε)), None: the plant's default;
        ``wire_noise_v``: Gaussian noise of the wire-voltage channel at the wire, V RMS, drawn
        per 1 ms step as the offline driver draws it (``SimCurrentSource`` in drivers/sim.py);
        the emulated firmware: per ADS1115 conversion, in the harness (``VNOISE``)."""
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"fault must be one of {', '.join(FAULTS)}, got {fault!r}")
        self.fault = fault
        self.fault_ms: float | None = None  # device time the fault began
        self.fault_report: str | None = None
        self._resets_at_fault = 0
        self._reset_reported = False
        if firmware not in FIRMWARES:
            raise ValueError(f"firmware must be one of {', '.join(FIRMWARES)}, got {firmware!r}")
        if not 0.0 < speed <= 100.0:
            raise ValueError(f"speed must be in (0, 100], got {speed}")
        if firmware == "emulated" and speed != 1.0:
            raise ValueError("the emulated firmware runs in real time only (speed 1)")
        if not 0.0 <= wire_noise_v < math.inf:
            raise ValueError(f"wire_noise_v must be ≥ 0 V, got {wire_noise_v}")
        self.wire_noise_v = wire_noise_v
        self._wire_noise_rng = np.random.default_rng(seed)
        if bootloader and firmware != "emulated":
            raise ValueError("--bootloader needs the emulated firmware (--firmware emulated)")
        if blank and not bootloader:
            raise ValueError("--blank needs --bootloader (a blank chip can only be flashed by one)")
        self.bootloader, self.blank = bootloader, blank
        self.sensor_map, self.adapter_latency_s = sensor_map, adapter_latency_s
        self.thermocouple = thermocouple
        self.link = PlantLink(load_kg, wire, effects, noise_mm=noise_mm, seed=seed, trace=trace,
                              resistivity=resistivity)  # fmt: skip
        self.speed = speed
        self.firmware = firmware
        self.realtime = realtime and speed <= REALTIME_MAX_SPEED
        self.tcp_port = tcp_port
        self.rtu = rtu
        self.device: SerialDevice | None = None
        self.emulated: EmulatedDriver | None = None
        self.server: SensorServer | None = None
        self._socat: subprocess.Popen | None = None
        self._links: tuple[str, ...] = ()  # the RTU pty pair's links (socat's)
        self.ports: MockPorts | None = None

    def _couple(self, t_ms: float, dt_s: float, fw: MockFirmware) -> Electrical:
        state = self.link.step(dt_s, fw.current_ma / 1000.0)
        noise_v = (self.wire_noise_v * float(self._wire_noise_rng.standard_normal())
                   if self.wire_noise_v else 0.0)  # fmt: skip
        return Electrical(
            resistance_ohm=state.resistance_ohm,
            wire_offset_v=noise_v,
            ambient_c=state.ambient_c,
            wire_temperature_c=state.temperature_c if self.thermocouple else None,
            fault=self._fault_now(t_ms, dt_s, fw),
        )

    def _fault_now(self, t_ms: float, dt_s: float, fw: MockFirmware) -> str | None:
        """The injected fault for this step: armed until the current first flows, then on (a hung
        MCU: until its watchdog has reset it); its outcome reported once the cut opened."""
        if self.fault is None:
            return None
        if self.fault_ms is None:
            if fw.current_ma < FAULT_ARM_MA:
                return None
            self.fault_ms = t_ms - dt_s * 1000.0  # it acts from the start of this step
            self._resets_at_fault = fw.watchdog_resets
            print(f"fault: {self.fault} at {self.fault_ms:.0f} ms (device time), wire current "
                  f"{fw.current_ma:.0f} mA", flush=True)
        if self.fault_report is None and fw.cut.events:
            event = fw.cut.events[-1]
            if event.t_ms >= self.fault_ms:
                self.fault_report = (
                    f"cut: opened by the {event.cause} {event.t_ms - self.fault_ms:.0f} ms after "
                    f"the {self.fault} (device time); wire current now {fw.current_ma:.0f} mA")
                print(self.fault_report, flush=True)
        if self.fault == "mcu-hang" and fw.watchdog_resets > self._resets_at_fault:
            if self.fault_report is not None and not self._reset_reported:
                self._reset_reported = True
                print(f"mcu: reset by its own watchdog at {t_ms:.0f} ms (device time)",
                      flush=True)
            return None  # the MCU's own watchdog reset it: the loop runs again
        return self.fault

    def _start_socat(self) -> tuple[str, str] | None:
        if not self.rtu or shutil.which("socat") is None:
            if self.rtu:
                log.warning("socat not installed: no Modbus RTU port (TCP only)")
            return None
        # the pair's links straight in the temporary folder, under a name no one else picks:
        # socat removes them when it ends, and it ends with this process (die_with_parent), even
        # when this process is killed; a private folder around them stayed behind after a SIGKILL
        stem = os.path.join(tempfile.gettempdir(), f"smabench-mock-{secrets.token_hex(8)}")
        server_end, client_end = f"{stem}-sensor-server", f"{stem}-sensor"
        self._links = (server_end, client_end)
        self._socat = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={server_end}", f"pty,raw,echo=0,link={client_end}"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=die_with_parent,
        )
        deadline = time.monotonic() + 5.0
        while not (os.path.exists(server_end) and os.path.exists(client_end)):
            if time.monotonic() > deadline or self._socat.poll() is not None:
                raise RuntimeError("socat did not create the RTU pty pair")
            time.sleep(0.01)
        return server_end, client_end

    def start(self) -> MockPorts:
        """Start every part; returns where to connect."""
        try:
            if self.firmware == "python":
                self.device = SerialDevice(
                    speed=self.speed, on_step=self._couple,
                    thread_priority=DEVICE_RT_PRIORITY if self.realtime else None,
                ).start()  # fmt: skip
                driver_port = self.device.port_name
            else:
                self.emulated = EmulatedDriver(
                    self.link,
                    bootloader=self.bootloader,
                    blank=self.blank,
                    thermocouple=self.thermocouple,
                    realtime=self.realtime,
                    fault=self.fault,
                    wire_noise_v=self.wire_noise_v,
                )
                driver_port = self.emulated.port_name
            rtu_ends = self._start_socat()
            self.server = SensorServer(
                self.sensor_map,
                tcp_port=self.tcp_port,
                serial_port=rtu_ends[0] if rtu_ends else None,
                adapter_latency_s=self.adapter_latency_s,
                parity="N",  # a pty refuses parity: an 8E1 map is served as 8N1 (rtu_spec says)
            )
            self.server.set_source("position", self.link.position_mm)
            self.server.start()
            rtu_spec = self.server.rtu_spec.replace(rtu_ends[0], rtu_ends[1]) if rtu_ends else None
            self.ports = MockPorts(driver_port, self.server.tcp_spec, rtu_spec)
        except BaseException:
            self.stop()
            raise
        log.info("mock bench up: %s", "; ".join(self.ports.lines()))
        return self.ports

    def stop(self) -> None:
        """Stop everything this bench started (idempotent)."""
        if self.server is not None:
            with contextlib.suppress(RuntimeError):
                self.server.stop()
            self.server = None
        if self.device is not None:
            self.device.stop()
            self.device = None
        if self.emulated is not None:
            self.emulated.stop()
            self.emulated = None
        if self._socat is not None:
            self._socat.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._socat.wait(2.0)
            self._socat = None
        for link in self._links:  # socat removed them when it ended; if it could not, here
            with contextlib.suppress(OSError):
                os.unlink(link)
        self._links = ()
        self.link.close()

    def __enter__(self) -> MockBench:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
