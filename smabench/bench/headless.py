"""Headless bench commands: ``smabench mock`` (serve the mock bench) and ``smabench run``.

``smabench run --mock`` starts ``smabench mock`` as a separate process, reads the port names it
prints and runs the session against them over the real transports, exactly as against hardware.
Every setting is validated before any device is opened.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from smabench import argtypes
from smabench import settings as settings_schema

if TYPE_CHECKING:
    from smabench.bench.session_run import RunSettings

log = logging.getLogger(__name__)

READY_LINE = "ready"
EXIT_ABORTED = 1


# --------------------------------------------------------------------------- smabench mock
def cmd_mock(args: argparse.Namespace) -> int:
    """Serve the mock bench until SIGINT/SIGTERM (or stdin EOF with --control-stdin)."""
    from smabench.bench.priority import raise_priority, realtime_process
    from smabench.drivers.mock.bench import MockBench
    from smabench.physics.effects import Effects
    from smabench.physics.resistance import RESISTIVITY_PRESETS

    raise_priority()  # it stands in for a microcontroller and a sensor: host load slows neither

    try:  # the hanging load's range is the run setting's (a simulated wire needs no confirmation)
        settings_schema.check_value("load_kg", args.load_kg)
    except settings_schema.SettingError as exc:
        raise ValueError(exc.naming("--load-kg")) from None
    bench = MockBench(
        args.load_kg,
        speed=args.speed,
        effects=Effects.from_strings(args.effect),
        firmware=args.firmware,
        tcp_port=args.tcp_port,
        seed=args.seed,
        trace=args.trace,
        bootloader=args.bootloader,
        blank=args.blank,
        sensor_map=args.sensor_map,
        adapter_latency_s=args.adapter_latency_ms / 1000.0,
        thermocouple=args.thermocouple,
        realtime=True,  # up to REALTIME_MAX_SPEED; the simavr harness too, started before
        fault=getattr(args, "fault", None),
        resistivity=RESISTIVITY_PRESETS[args.resistivity] if args.resistivity else None,
        wire_noise_v=args.wire_noise_v,
    )
    if not args.verbose:  # pymodbus logs an ERROR with a frame dump for every dropped client
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        if args.control_stdin:  # a child of `run`/`plan`, which say the session's problems once
            logging.getLogger("smabench").setLevel(logging.ERROR)
    done = threading.Event()  # set by the stdin control thread (EOF, quit)
    signalled: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        # only a list append, no lock: a handler that called done.set() deadlocked the mock when
        # a second signal (SIGTERM on the parent's death, then SIGHUP) interrupted the first
        # handler inside the Event's lock (an orphaned real-time mock, seen with gdb)
        signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    ports = bench.start()
    if bench.realtime:
        # its threads (the driver's device thread, the sensor's server) then answer within the
        # scheduler's real-time latency whatever else runs, as the microcontroller and sensor
        # do: a nice value alone loses to every process at the same nice (tests run at −10) and
        # to other sessions' process groups (autogroup). At 5× its device thread takes 48 % of a
        # core and its Modbus server 20 % (measured, fb7eda0): two 5× mocks with their runs
        # can exceed the kernel's real-time budget (RT throttling; open, see
        # drivers/mock/serial_device.WAKE_S); a faster mock keeps normal scheduling
        realtime_process()
    try:
        print(
            f"mock bench: {args.load_kg} kg, speed {args.speed}×, firmware {args.firmware}"
            + (f", effects {', '.join(args.effect)}" if args.effect else "")
            + (f", resistivity {args.resistivity}" if args.resistivity else "")
            + (", bootloader" if args.bootloader else "")
            + (" on a blank flash" if args.blank else "")
        )
        for line in ports.lines():
            print(line)
        print(READY_LINE, flush=True)
        if args.control_stdin:
            threading.Thread(
                target=_control_loop, args=(bench, done), name="mock-control", daemon=True
            ).start()
        while not (signalled or done.is_set()):
            time.sleep(0.2)
    finally:
        # a stop that hangs (seen once: an orphaned real-time mock still running 21 min after
        # its parent died) must not leave a real-time process behind: exit anyway after 10 s
        guard = threading.Timer(MOCK_STOP_LIMIT_S, _exit_stuck_mock)
        guard.daemon = True
        guard.start()
        bench.stop()
        guard.cancel()
    return 0


MOCK_STOP_LIMIT_S = 10.0
"""Longest wait for the mock bench to stop before the process exits regardless, s."""


def _exit_stuck_mock() -> None:
    log.error("mock bench did not stop within %.0f s: exiting", MOCK_STOP_LIMIT_S)
    os._exit(1)


def _control_loop(bench, done: threading.Event) -> None:
    """Fault injection from stdin, one command per line (for tests and demos):
    ``sensor-delay S N`` (N responses late by S s), ``sensor-exception CODE N``,
    ``sensor-corrupt N``, ``sensor-status-error N`` / ``sensor-sentinel N`` (the map's error
    status / "no measurement" code for N requests), ``sensor-freeze N`` (the same reading for N
    requests), ``sensor-drop S`` (no answer at all for S s of wall time: every request then
    times out, as a sensor that stopped answering), ``open-wire``, ``close-wire``, ``quit``.
    EOF ends the mock."""
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        try:
            cmd, rest = words[0], words[1:]
            if cmd == "sensor-delay":
                bench.server.delay_responses(float(rest[0]), int(rest[1]))
            elif cmd == "sensor-exception":
                bench.server.fail_with_exception(int(rest[0]), int(rest[1]))
            elif cmd == "sensor-corrupt":
                bench.server.corrupt_responses(int(rest[0]))
            elif cmd == "sensor-status-error":
                bench.server.serve_status_error(int(rest[0]))
            elif cmd == "sensor-sentinel":
                bench.server.serve_sentinel(int(rest[0]))
            elif cmd == "sensor-freeze":  # the same reading, valid, for N requests
                bench.server.freeze(int(rest[0]))
            elif cmd == "sensor-drop":  # no answer for S seconds
                bench.server.drop_for(float(rest[0]))
            elif cmd in ("open-wire", "close-wire") and bench.device is not None:
                bench.device.set_open_wire(cmd == "open-wire")
            elif cmd == "quit":
                break
            else:
                print(f"mock: unknown command {line.strip()!r}", file=sys.stderr, flush=True)
                continue
            print(f"ok {cmd}", flush=True)
        except (IndexError, KeyError, ValueError) as exc:
            print(f"mock: bad command {line.strip()!r}: {exc}", file=sys.stderr, flush=True)
    done.set()


@dataclass
class MockPortsSeen:
    driver: str
    sensor_tcp: str
    sensor_rtu: str | None


class MockError(RuntimeError):
    """The mock bench did not start (exited, or not ready within its readiness timeout)."""


READY_TIMEOUT_ENV = "SMABENCH_MOCK_READY_TIMEOUT_S"


def ready_timeout_s() -> float:
    """The mock's readiness timeout, s: ``$SMABENCH_MOCK_READY_TIMEOUT_S`` or the declared
    default (``mock.ready_timeout_s`` in :mod:`smabench.settings`); ValueError naming the
    variable when it is not a number in range."""
    setting = settings_schema.DEVICE_OPTIONS["mock.ready_timeout_s"]
    text = os.environ.get(READY_TIMEOUT_ENV)
    if text is None:
        return float(setting.default)
    try:
        return float(setting.check(text))
    except settings_schema.SettingError as exc:
        raise ValueError(f"{exc.reason} (environment variable {READY_TIMEOUT_ENV})") from None


class MockProcess:
    """``smabench mock`` in its own process; :attr:`ports` once it is ready. ``timeout_s``
    (default :func:`ready_timeout_s`): its start-up, an interpreter and its imports, takes
    1-2 s on a quiet machine and over 20 s beside other work on two cores; when it is not
    ready by then the process is ended and :class:`MockError` raised (one line)."""

    def __init__(self, mock_args: list[str], timeout_s: float | None = None) -> None:
        from smabench.drivers.mock.bench import die_with_parent

        timeout_s = ready_timeout_s() if timeout_s is None else timeout_s
        # it also ends on stdin EOF, i.e. when this process dies, whatever the signal; -P: the
        # installed smabench, never a smabench/ folder in the working directory (a checkout)
        self.proc = subprocess.Popen(
            [sys.executable, "-P", "-m", "smabench.cli", "mock", "--control-stdin", *mock_args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
            preexec_fn=die_with_parent,
            start_new_session=True,  # the bench's stand-in: a terminal's Ctrl-C or hang-up
        )  # reaches the session (which makes it safe), not the devices
        # a reader thread: the wait below is bounded whether or not the mock prints anything
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True, name="mock-stdout")
        self._reader.start()
        found: dict[str, str] = {}
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self._lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                self.close(kill=True)
                raise MockError(f"mock bench did not become ready within {timeout_s:g} s "
                                f"(a loaded machine? {READY_TIMEOUT_ENV} sets the wait)") from None
            if line is None:
                code = self.proc.wait()
                raise MockError(f"mock bench exited with code {code} before it was ready")
            line = line.strip()
            if line == READY_LINE:
                break
            key, sep, value = line.partition(": ")
            if sep:
                found[key] = value
        self.ports = MockPortsSeen(found["driver"], found["sensor-tcp"], found.get("sensor-rtu"))

    def _read(self) -> None:
        """Hand the mock's lines to the readiness wait, then drain them (it never blocks)."""
        ready = False
        for line in self.proc.stdout:
            if not ready:
                self._lines.put(line)
                ready = line.strip() == READY_LINE
        self._lines.put(None)

    def send(self, command: str) -> None:
        """One fault-injection command (see ``_control_loop``)."""
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def kill(self) -> None:
        """SIGKILL: the bench disappears at once, as a cable pulled out."""
        self.proc.kill()
        self.proc.wait()

    def close(self, kill: bool = False) -> None:
        if self.proc.poll() is None:
            if kill:  # not ready: it may be stuck anywhere in its start-up
                self.proc.kill()
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.close()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self) -> MockProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def add_mock_arguments(s: argparse.ArgumentParser, prefix: str = "") -> None:
    """Options of the mock bench (``--load-kg`` etc.; with a prefix for ``smabench run``)."""
    s.add_argument(f"--{prefix}speed", type=settings_schema.arg_type("time_scale"), default=1.0,
                   metavar="X",
                   help="simulation speed, × real time (0.1 … 100; 1)")
    s.add_argument(
        f"--{prefix}effect",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="switch on a plant effect (repeatable; `smabench simulate --list-effects`)",
    )
    s.add_argument(
        f"--{prefix}firmware",
        choices=["python", "emulated"],
        default="python",
        help="current driver: the Python firmware model, or the real firmware in simavr",
    )
    s.add_argument(f"--{prefix}seed", type=settings_schema.arg_type("mock.seed"), default=0,
                   metavar="N",
                   help="sensor noise seed (0 … 1e9; 0)")
    s.add_argument(
        f"--{prefix}adapter-latency-ms",
        type=settings_schema.arg_type("mock.adapter_latency_ms"),
        default=0.0,
        metavar="MS",
        help="hold every sensor answer this long, as an FTDI USB/RS-485 adapter's latency timer "
        "does (0 … 1000 ms; 16 ms by default on a real one)",
    )
    s.add_argument(f"--{prefix}wire-noise-v", type=settings_schema.arg_type("mock.wire_noise_v"),
                   default=0.0, metavar="V",
                   help="Gaussian noise of the driver's wire-voltage channel, V RMS at the "
                   "wire, per 1 ms step (emulated firmware: per conversion; 0 … 0.01; 0)")
    s.add_argument(
        f"--{prefix}trace",
        metavar="FILE.csv",
        help="write what the plant really got (t_s, current_A, temperature_C, position_mm)",
    )
    s.add_argument(
        f"--{prefix}thermocouple",
        action="store_true",
        help="a MAX31855 thermocouple on the wire reports its temperature (temperature_C)",
    )
    s.add_argument(
        f"--{prefix}resistivity",
        choices=["flexinol", "flexinol-rphase"],
        default=None,
        help="the wire's resistance from this resistivity model, R(ξ, T, ε) (issue 26; "
        "flexinol-rphase: with an R-phase on cooling), so the wire voltage the driver measures "
        "is I·R; default: the plant's two-phase resistance",
    )


# --------------------------------------------------------------------------- smabench run
def settings_from_args(args: argparse.Namespace) -> RunSettings:
    """RunSettings from the command line (options derived from :mod:`smabench.settings`);
    ValueError naming the option, its value and range when refused (nothing opened yet)."""
    from smabench.bench.session_run import RunSettings  # the control stack: imported on use
    try:
        given = settings_schema.values_from_args(args)
        if given.get("controller.switches") and given.get("controller.mode") is None:
            given["controller.mode"] = "pid"  # a switch needs a controller to switch
        settings = RunSettings.from_values(given)
    except settings_schema.SettingError as exc:
        raise ValueError(settings_schema.cli_error(exc)) from None
    if args.mock:
        try:
            settings.time_scale = settings_schema.check_value("time_scale", args.mock_speed)
        except settings_schema.SettingError as exc:
            raise ValueError(exc.naming("--mock-speed")) from None
    try:
        settings.validate()
    except settings_schema.SettingError as exc:
        raise ValueError(settings_schema.cli_error(exc)) from None
    return settings


def _progress_printer(protocol, total: int, every_s: float = 1.0):
    last = [-math.inf]

    def on_sample(row: dict) -> None:
        now = time.monotonic()
        est = row.get("position_est_mm")
        est_text = "" if est is None else f"  x̂ {est:.4f} mm"  # with a self-sense calibration
        if now - last[0] >= every_s and row["setpoint_mm"] is not None:
            last[0] = now
            print(
                f"  t {row['t_s']:7.1f} s  cycle {row['cycle'] + 1}/{total}  {row['mode']:9s} "
                f"I {row['current_A']:.3f} A  T≈{row['temperature_est_C']:6.1f} °C  "
                f"x {row['position_mm']:.4f} mm{est_text}  set {row['setpoint_mm']:.4f} mm",
                flush=True,
            )
        elif now - last[0] >= every_s:
            last[0] = now
            print(
                f"  t {row['t_s']:7.1f} s  cycle {row['cycle'] + 1}/{total}  "
                f"{protocol.phase:5s}  I {row['current_A']:.3f} A  "
                f"T≈{row['temperature_est_C']:6.1f} °C  x {row['position_mm']:.4f} mm{est_text}",
                flush=True,
            )

    return on_sample


def open_devices(
    port: str,
    spec: str,
    settings: RunSettings,
    sensor_map: str = "generic-rs485-laser",
    sensor_timeout_s: float = 0.05,
    unit_id: int | None = None,
):
    """Connect the current driver and the sensor for a session; returns (source, sensor).
    ``unit_id`` overrides the register map's Modbus unit id.

    The settings are checked again against the driver's hard limit before anything but the
    handshake is sent; latched faults from before the session are cleared.
    """
    from smabench.bench.priority import LINK_RT_PRIORITY, raise_priority
    from smabench.drivers import protocol as p
    from smabench.drivers.current_source import CurrentSource
    from smabench.drivers.displacement import DisplacementSensor

    raise_priority()  # every process that runs sessions (run, plan, bench control, the GUI's)
    scale = settings.time_scale  # the device's clocks run `scale` × faster on a fast mock
    source = CurrentSource(
        port,
        current_limit_a=settings.current_limit_a,
        host_timeout_s=min(5.0, 0.25 * scale),
        lease_s=min(5.0, p.LEASE_DEFAULT_S * scale),  # the setpoint lease, in device time
        telemetry_period_s=min(1.0, 0.01 * scale),
        owner_priority=LINK_RT_PRIORITY,  # keepalive and telemetry: not held up by host load
    )
    try:
        info = source.connect()
        settings.validate(device_limit_a=info.hard_limit_a)
        source.clear_faults()
        source.get_calibration()  # as read back at connect: session.json's calibration block
        sensor = DisplacementSensor(
            sensor_map, spec, timeout_s=sensor_timeout_s, retries=0, unit_id=unit_id
        )
        sensor.connect()
    except BaseException:
        source.close()
        raise
    return source, sensor


def cmd_run(args: argparse.Namespace) -> int:
    if args.mock == bool(args.port):
        raise ValueError("give either --mock or --port DEV --sensor SPEC")
    if args.port and not args.sensor:
        raise ValueError("--port needs --sensor (tcp:HOST:PORT or rtu:DEVICE[:BAUD])")
    settings = settings_from_args(args)  # everything checked before a device is opened
    from smabench.bench.session_run import check_session_space, run_session
    from smabench.protocols import Protocol
    ready_s = ready_timeout_s() if args.mock else None  # the environment's setting too
    if args.port:  # a missing device is said now, not after the driver's open retries
        try:
            argtypes.serial_port(args.port)
        except argparse.ArgumentTypeError as exc:
            raise ValueError(f"argument --port: {exc}") from None
    from smabench.bench.priority import raise_priority

    raise_priority()  # the control loop (and the mock it starts) before other work
    if args.mock and args.mock_resistivity:
        from smabench.physics.effects import Effects

        if Effects.from_strings(args.mock_effect).phase_resistance:
            raise ValueError("--mock-resistivity replaces the phase_resistance effect: give one "
                             "of them")  # fmt: skip
    cal = settings.selfsense_calibration()
    if cal is not None and cal.load_kg is not None and cal.load_kg != settings.load_kg:
        print(f"note: the self-sense calibration was taken at {cal.load_kg:g} kg, this session "
              f"runs at {settings.load_kg:g} kg (the estimate's error grows: re-take it)",
              flush=True)  # fmt: skip
    stress = settings.stress()
    if stress.needs_confirmation:  # allowed with --allow-high-stress, else refused above
        print(f"note: {settings.load_kg:g} kg puts {stress.stress_mpa:.0f} MPa on the wire, "
              f"above the wire's long-life stress of {stress.limit_mpa:.0f} MPa "
              "(--allow-high-stress; recorded in session.json)", flush=True)
    mock = None
    mock_args: list[str] = []
    source = sensor = None
    check_session_space(settings)  # a full or read-only --out is refused before any device
    for sig in (signal.SIGTERM, signal.SIGHUP):  # before the session: end like Ctrl-C (130);
        signal.signal(sig, _interrupt)  # during it: aborted, closed, 1 (run_session's handlers)
    try:
        if args.mock:
            mock_args = [
                *("--load-kg", f"{settings.load_kg:g}", "--speed", str(args.mock_speed)),
                *("--firmware", args.mock_firmware, "--seed", str(args.mock_seed)),
            ]
            for e in args.mock_effect:
                mock_args += ["--effect", e]
            if args.mock_trace:
                mock_args += ["--trace", str(Path(args.mock_trace).resolve())]
            if args.mock_thermocouple:
                mock_args += ["--thermocouple"]
            if args.mock_resistivity:
                mock_args += ["--resistivity", args.mock_resistivity]
            mock_args += ["--sensor-map", args.sensor_map]  # it serves what the client reads
            mock_args += ["--adapter-latency-ms", f"{args.mock_adapter_latency_ms:g}"]
            if args.mock_wire_noise_v:
                mock_args += ["--wire-noise-v", f"{args.mock_wire_noise_v:g}"]
            mock = MockProcess(mock_args, ready_s)
            port = mock.ports.driver
            spec = mock.ports.sensor_rtu if args.mock_sensor == "rtu" else mock.ports.sensor_tcp
            if spec is None:
                raise ValueError("the mock bench has no RTU port (socat missing)")
        else:
            port, spec = args.port, args.sensor
        source, sensor = open_devices(port, spec, settings, args.sensor_map, args.sensor_timeout_s)
        info = source.info
        devices = {
            "current_driver": {"port": port, **dataclasses.asdict(info)},
            "sensor": {"spec": spec, "map": sensor.map.name},
            "mock": mock_args if args.mock else None,
        }
        total = settings.protocol.cycles
        if settings.controller is not None:
            protocol = settings.build_controller()
            ref = protocol.info["reference"]
            print(
                f"session: {settings.protocol.name} reference, {total} period(s) of "
                f"{ref['period_s']:g} s, {ref['offset_mm']:.3f} ± {ref['amplitude_mm']:g} mm "
                f"under {settings.load_kg} kg, controller {protocol.mode}, "
                f"{settings.rate_hz:g} Hz loop",
                flush=True,
            )
        else:
            protocol = Protocol(settings.protocol)
            print(
                f"session: {settings.protocol.name}, {total} cycle(s) at "
                f"{settings.protocol.current_a} A under {settings.load_kg} kg, "
                f"{settings.rate_hz:g} Hz loop",
                flush=True,
            )
        folder, result = run_session(
            settings,
            source,
            sensor,
            devices,
            on_sample=None if args.quiet else _progress_printer(protocol, total),
            command=protocol,
        )
    finally:
        for dev in (source, sensor):
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.make_safe()
                with contextlib.suppress(Exception):
                    dev.close()
        if mock is not None:
            mock.close()
    print(f"session: {folder}")
    print(f"{result.status}: {result.reason} ({result.samples} samples)")
    if result.status != "completed":
        print(f"smabench run: {result.status}: {result.reason}", file=sys.stderr)
        return EXIT_ABORTED
    return 0


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def add_device_options(parser, mock_help: str, port_type) -> None:
    """``--mock``, ``--port``, ``--sensor``, ``--sensor-map``: the devices of a run or a plan,
    declared once. ``port_type``: the port's check (``run`` checks its existence after the
    settings, so that a setting's error is named first)."""
    parser.add_argument("--mock", action="store_true", help=mock_help)
    parser.add_argument("--port", type=port_type, metavar="DEV",
                        help="current driver serial port, e.g. /dev/ttyUSB0")
    parser.add_argument("--sensor", type=argtypes.sensor_spec, metavar="SPEC",
                        help="displacement sensor: tcp:HOST:PORT or rtu:DEV[:BAUD]")
    parser.add_argument("--sensor-map", type=argtypes.sensor_map,
                        default="generic-rs485-laser", metavar="MAP",
                        help="register map: a shipped name or a map file")


def add_commands(sub) -> None:
    """Register ``mock`` and ``run`` on the CLI's subparsers."""
    s = sub.add_parser("mock", help="serve the mock bench over real transports, print its ports")
    s.add_argument("--load-kg", type=settings_schema.arg_type("load_kg"), default=2.0,
                   metavar="KG", help="hanging load, kg (default 2)")
    s.add_argument("--tcp-port", type=settings_schema.arg_type("mock.tcp_port"), default=0,
                   metavar="PORT",
                   help="Modbus TCP port (0 = any free)")
    s.add_argument(  # internal: how `run --mock` and the tests drive it
        "--control-stdin", action="store_true", help=argparse.SUPPRESS
    )
    add_mock_arguments(s)
    s.add_argument(
        "--sensor-map",
        type=argtypes.sensor_map,
        default="generic-rs485-laser",
        metavar="MAP",
        help="register map the sensor serves (a shipped name or a map file)",
    )
    s.add_argument(
        "--bootloader",
        action="store_true",
        help="emulated firmware: boot optiboot first; every open of the port resets it, as a Nano",
    )
    s.add_argument(
        "--blank", action="store_true", help="with --bootloader: no application (flash it first)"
    )
    s.add_argument(
        "--fault",
        choices=["mosfet-short", "wire-to-ground", "mcu-hang"],
        help="inject a fault once the wire current first exceeds 0.5 A and print what the "
        "hardware cut did and when (device time)",
    )
    s.set_defaults(func=cmd_mock)

    s = sub.add_parser("run", help="run a recorded session (headless) on the bench or the mock")
    where = s.add_argument_group("devices")
    add_device_options(where, "start and use the mock bench", argtypes.port_syntax)
    where.add_argument(
        "--sensor-timeout-s",
        type=settings_schema.arg_type("sensor_timeout_s"),
        metavar="S",
        default=0.05,
        help="per-request Modbus timeout in the loop, s (0.001 … 5; 0.05); a late reading is "
        "flagged",
    )
    where.add_argument(
        "--mock-sensor", choices=["tcp", "rtu"], default="tcp", help="mock sensor transport"
    )
    add_mock_arguments(where, prefix="mock-")
    settings_schema.add_cli_options(s)  # every run setting, from the one schema
    s.add_argument("--quiet", action="store_true", help="no progress lines")
    s.set_defaults(func=cmd_run)

