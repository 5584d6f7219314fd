"""The host driver and every safety path against the REAL firmware (ATmega328P build) in simavr.

Harness: ``firmware/build/sim/smabench-sim ELF`` prints ``PTY <path>`` on stdout, then takes
control commands on stdin: ``R <ohms>`` (wire resistance), ``V <volts>`` (supply), ``OPEN``
(open wire), ``ESTOP 0|1``, ``TC <celsius>|NONE|OC|SCG|SCV`` (the MAX31855), ``NTC OK|OPEN|SHORT``,
``ADS 0|1`` (the ADS1115), ``Q`` (answers ``STATE t_ms=.. duty=.. current_a=.. …``). Build with
``make -C firmware elf sim`` (``make test`` does). Skipped when missing, except under CI.

Timing is checked in device time (the telemetry's ``t_ms``) and on the device side (the
harness's wire current), never against the wall clock: on a loaded machine the emulator runs at
55–70 % of real time and the host may read late. Every telemetry frame is kept in order
(:class:`Frames`, :class:`RawDevice`), none skipped; host deadlines are generous and only bound
a wait. The driver here never resends a command (``retries=0``): a resent SET_CURRENT or ENABLE
would restart the lease at a time no frame shows. The new commands (calibration, heat model) go
through :class:`RawDevice`, a minimal client on the shared codec.
"""

from __future__ import annotations

import contextlib
import math
import os
import queue
import re
import select
import subprocess
import threading
import time
import tty
from pathlib import Path

import pytest

from smabench.drivers import protocol as p
from smabench.drivers.current_source import CurrentSource, DeviceFault, VersionMismatch
from smabench.drivers.mock.bench import realtime_child

REPO = Path(__file__).resolve().parent.parent
SIM = Path(os.environ.get("SMABENCH_SIM", REPO / "firmware/build/sim/smabench-sim"))
ELF = Path(os.environ.get("SMABENCH_ELF", REPO / "firmware/build/avr/smabench-cd.elf"))
F = p.Flag

_MISSING = [str(path) for path in (SIM, ELF) if not path.is_file()]

pytestmark = [
    pytest.mark.emulator,
    pytest.mark.slow,  # a simavr process per test
    pytest.mark.timeout(120),
    # `make test` builds both first; under CI a missing build is a failure, never a skip
    pytest.mark.skipif(
        bool(_MISSING) and not os.environ.get("CI"),
        reason=f"firmware build missing: {_MISSING} (build it with `make -C firmware elf sim`)",
    ),
    pytest.mark.realtime_bench,
]

SETTLING_MS = 50  # PROTOCOL.md: within 5 % of a step within 50 ms
HOST_TIMEOUT_S = 0.25
TELEMETRY_MS = 5  # the telemetry period the fixtures set
WAIT_S = 10.0  # host deadline for a device event: bounds a wait, measures nothing
M = p.MsgType
S = p.Status


class Harness:
    """The simavr harness process: PTY path, stdin control, STATE queries. It stands in for a
    microcontroller, which host load does not slow: CPU-favoured where allowed, as the mock
    bench runs it (:func:`~smabench.drivers.mock.bench.realtime_child`)."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [str(SIM), *(args or (str(ELF),))],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
            preexec_fn=realtime_child,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.stderr: list[str] = []
        self._err_cond = threading.Condition()
        threading.Thread(target=self._read_err, daemon=True).start()
        line = self._expect("PTY ", 30.0)
        self.port_name = line.split(None, 1)[1].strip()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._err_cond:
                self.stderr.append(line)
                self._err_cond.notify_all()

    def wait_stderr(self, text: str, start: int, timeout_s: float = WAIT_S) -> int:
        """Index of the first stderr line from ``start`` on that contains ``text``."""
        deadline = time.monotonic() + timeout_s
        with self._err_cond:
            while True:
                for i in range(start, len(self.stderr)):
                    if text in self.stderr[i]:
                        return i
                left = deadline - time.monotonic()
                assert left > 0, f"harness never said {text!r}: {''.join(self.stderr[-10:])}"
                self._err_cond.wait(left)

    def wait_device_ms(self, t_ms: float) -> None:
        """Until the AVR has run ``t_ms`` since power-on (harness time)."""
        deadline = time.monotonic() + WAIT_S
        while self.state()["t_ms"] < t_ms:
            assert time.monotonic() < deadline, f"the AVR did not reach {t_ms} ms"
            time.sleep(0.001)

    def wait_ready_after_reset(self, line: int) -> None:
        """Until the firmware listens after the reset reported on stderr line ``line`` (PROTOCOL.md
        "Readiness after reset": p.READY_AFTER_RESET_S of device time). A frame sent at once
        after the harness says "reset" can reach the AVR before its UART is on, and is lost as
        on the real part (seen on a busy host: no ACK)."""
        m = re.search(r"reset at t=([\d.]+) ms", self.stderr[line])
        assert m, self.stderr[line]
        self.wait_device_ms(float(m.group(1)) + p.READY_AFTER_RESET_S * 1e3)

    def _expect(self, prefix: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                raise AssertionError(
                    f"harness: no '{prefix}' line (exit {self.proc.poll()}); "
                    f"stderr: {''.join(self.stderr[-20:])}"
                )
            try:
                line = self.lines.get(timeout=min(left, 0.1))
            except queue.Empty:
                continue
            if line.startswith(prefix):
                return line

    def send(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def state(self) -> dict[str, float]:
        self.send("Q")
        line = self._expect("STATE", WAIT_S)
        out = {}
        for tok in line.split()[1:]:
            k, _, v = tok.partition("=")
            out[k] = float(v)
        return out

    def set_resistance(self, ohm: float) -> None:
        self.send(f"R {ohm}")

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError):  # EOF on stdin, then terminate
                self.proc.stdin.close()
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)


@pytest.fixture
def sim():
    h = Harness()
    yield h
    h.close()


@pytest.fixture
def cs(sim):
    # no resends (a late ACK under load is waited for, not answered by a second command) and a
    # link that a busy host does not declare lost (which would redo the handshake mid-test)
    src = CurrentSource(
        sim.port_name, telemetry_period_s=TELEMETRY_MS / 1e3, ack_timeout_s=1.0, retries=0,
        link_timeout_s=3.0, connect_wait_s=15.0,
    )  # fmt: skip
    src.connect()
    src.set_lease(5.0)  # these tests hold a setpoint without renewing it; the lease has its own
    yield src
    src.close()


class Frames:
    """Every telemetry frame the driver delivers, in order (a subscription: none skipped, unlike
    ``wait_telemetry`` which sees only the latest when the host reads late)."""

    def __init__(self, src: CurrentSource) -> None:
        self.items: list[p.Telemetry] = []
        self._cond = threading.Condition()
        self.unsubscribe = src.subscribe(self._add)

    def _add(self, t: p.Telemetry) -> None:
        with self._cond:
            self.items.append(t)
            self._cond.notify_all()

    def mark(self) -> int:
        """Index of the next frame to arrive."""
        with self._cond:
            return len(self.items)

    def find(self, pred=lambda t: True, start: int | None = None, timeout_s: float = WAIT_S):
        """(index, frame) of the first frame from ``start`` (default: the next one) on that
        satisfies ``pred``; AssertionError after ``timeout_s`` of host time."""
        i = self.mark() if start is None else start
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                while i < len(self.items):
                    if pred(self.items[i]):
                        return i, self.items[i]
                    i += 1
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.items[-1] if self.items else None
                    raise AssertionError(f"no matching telemetry within {timeout_s} s: {last}")
                self._cond.wait(left)

    def wait(self, pred=lambda t: True, start: int | None = None, timeout_s: float = WAIT_S):
        return self.find(pred, start, timeout_s)[1]


@pytest.fixture
def tel(cs):
    frames = Frames(cs)
    yield frames
    frames.unsubscribe()


class RawDevice:
    """A minimal client on the shared codec: commands and ACKs, telemetry frames."""

    def __init__(self, port: str) -> None:
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.rx = p.FrameReceiver()
        self.seq = 0
        self.pending: list[p.Packet] = []

    def close(self) -> None:
        os.close(self.fd)

    def send(self, type_: int, payload: bytes = b"") -> int:
        seq = self.seq
        self.seq = (self.seq + 1) & 0xFF
        os.write(self.fd, p.encode_frame(seq, type_, payload))
        return seq

    def _next(self, timeout_s: float) -> p.Packet | None:
        end = time.monotonic() + timeout_s
        while not self.pending:
            left = end - time.monotonic()
            if left <= 0:
                return None
            r, _, _ = select.select([self.fd], [], [], left)
            if r:
                self.pending += self.rx.feed(os.read(self.fd, 4096))
        return self.pending.pop(0)

    def command(self, type_: int, payload: bytes = b"", timeout_s: float = 5.0) -> p.Ack:
        seq = self.send(type_, payload)
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            pkt = self._next(left)
            if pkt is not None and pkt.type == M.ACK:
                ack = p.Ack.from_payload(pkt.payload)
                if ack.seq == seq and ack.type == type_:
                    return ack
        raise AssertionError(f"no ACK for {M(type_).name}")

    def status(self, type_: int, payload: bytes = b"") -> S:
        return S(self.command(type_, payload).status)

    def telemetry(self, pred=lambda t: True, timeout_s: float = WAIT_S) -> p.Telemetry:
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            pkt = self._next(left)
            if pkt is not None and pkt.type == M.TELEMETRY:
                t = p.Telemetry.from_payload(pkt.payload)
                if pred(t):
                    return t
        raise AssertionError(f"no matching telemetry within {timeout_s} s")

    def until(self, pred, timeout_s: float = WAIT_S) -> list[p.Telemetry]:
        """Every telemetry frame up to and including the first that satisfies ``pred``."""
        out: list[p.Telemetry] = []
        self.telemetry(lambda t: out.append(t) or pred(t), timeout_s)
        return out


@pytest.fixture
def raw(sim):
    dev = RawDevice(sim.port_name)
    # PROTOCOL.md "Readiness": the firmware listens from p.READY_AFTER_RESET_S after reset (no
    # bootloader here: the harness powers the AVR on when it starts)
    sim.wait_device_ms(p.READY_AFTER_RESET_S * 1e3)
    assert S(dev.command(*p.identify(), timeout_s=WAIT_S).status) == S.OK
    assert dev.status(*p.set_limits(2.5, 5.0)) == S.OK  # host timeout: a busy host is no fault here
    assert dev.status(*p.set_telemetry(TELEMETRY_MS / 1e3)) == S.OK
    yield dev
    dev.close()


def wait_until(cond, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.005)




# ------------------------------------------------------------------ the driver on the firmware
def test_handshake_and_version(cs):
    assert cs.info == p.DeviceInfo(4, (4, 0, 0), 2.5, "SMA-CD328")
    assert cs.link_ok
    t = cs.wait_telemetry(timeout_s=WAIT_S)
    assert not t.enabled and t.duty == 0.0
    rts = sorted(cs.ping() for _ in range(20))
    print(f"\nPING round trip to the emulated firmware: median {rts[10] * 1e3:.2f} ms")


def test_version_mismatch(sim):
    src = CurrentSource(sim.port_name, protocol_version=1, ack_timeout_s=1.0)
    with pytest.raises(VersionMismatch):
        src.connect()
    src.close()


def test_set_current_follows(cs, tel, sim):
    sim.set_resistance(0.44)
    cs.set_current(1.0, wait=True)
    start = tel.mark()
    cs.enable(True)
    i, first = tel.find(lambda t: t.enabled and t.setpoint_a == pytest.approx(1.0), start)
    j, settled = tel.find(lambda t: abs(t.current_a - 1.0) <= 0.05, i)
    assert settled.t_ms - first.t_ms <= SETTLING_MS + 10
    # and it stays there (PROTOCOL.md: within 5 %), frame by frame for 50 ms of device time
    k, _ = tel.find(lambda t: t.t_ms >= settled.t_ms + 50, j)
    assert all(abs(t.current_a - 1.0) <= 0.05 for t in tel.items[j : k + 1])
    state = sim.state()
    assert state["duty"] > 0
    assert state["current_a"] == pytest.approx(1.0, abs=0.01)
    # the Kelvin voltage and the precise current give the wire's resistance
    # (V and I alternate on the ADS1115 every 8 ms: both after the step, 50 ms later)
    t = tel.wait(lambda t: t.t_ms > settled.t_ms + 50, j)
    assert t.resistance_ohm == pytest.approx(0.44, rel=0.002)
    cs.make_safe()
    tel.wait(lambda t: not t.enabled and t.duty == 0.0)


def test_the_wire_channels_noise_reaches_the_telemetry(cs, tel, sim):
    """`VNOISE` (smabench mock --firmware emulated --wire-noise-v): Gaussian noise on the
    emulated ADS1115's wire channel, one draw per conversion. At 2 mV RMS at the wire the frames'
    V/I spread by 2 mV / √4 (a window averages 4 conversions) / 0.44 V = 0.23 % of R around the
    wire's R; quiet, by the 0.1 mV steps alone. A value out of range is refused on stderr."""
    import numpy as np

    sim.set_resistance(0.44)
    cs.set_current(1.0, wait=True)
    cs.enable(True)
    settled = tel.wait(lambda t: abs(t.current_a - 1.0) <= 0.02)

    def spread(after_ms: float) -> tuple[float, float]:
        start = tel.mark()
        k, _ = tel.find(lambda t: t.t_ms >= after_ms + 400, start)
        r = np.array([t.voltage_v / t.current_a for t in tel.items[start : k + 1]
                      if t.t_ms > after_ms + 20])  # fmt: skip
        return float(np.mean(r)), float(np.std(r) / np.mean(r))

    quiet_r, quiet_sd = spread(settled.t_ms)
    line = len(sim.stderr)
    sim.send("VNOISE -1")
    sim.wait_stderr("VNOISE takes", line)
    sim.send("VNOISE 0.002")
    noisy_r, noisy_sd = spread(tel.items[-1].t_ms)
    print(f"\nV/I quiet {quiet_r:.5f} Ω ± {quiet_sd * 100:.3f} %, with 2 mV RMS "
          f"{noisy_r:.5f} Ω ± {noisy_sd * 100:.3f} %")
    assert quiet_sd < 0.0006 and quiet_r == pytest.approx(0.44, rel=0.003)
    assert 0.0015 < noisy_sd < 0.0035 and noisy_r == pytest.approx(0.44, rel=0.003)
    cs.make_safe()


def test_clamping(cs, tel):
    cs.set_limits(0.8, 1.0)
    assert cs.set_current(1.5, wait=True) == p.Status.CLAMPED
    cs.enable(True)
    t = tel.wait(lambda t: abs(t.current_a - 0.8) <= 0.05)
    assert t.setpoint_a == pytest.approx(0.8)


def test_host_timeout_turns_output_off(cs, tel, sim):
    cs.set_limits(cs.info.hard_limit_a, HOST_TIMEOUT_S)
    cs.set_current(1.0, wait=True)
    cs.enable(True)
    tel.wait(lambda t: t.current_a > 0.9)
    cs.pause_keepalive()
    # the last frame the device gets is our PING: it arrived after frame `before - 1` (received
    # before it was sent) and before frame `after` (it follows the PING's ACK on the wire)
    before = tel.mark()
    cs.ping()
    after = tel.mark()
    _, off = tel.find(lambda t: not t.enabled, after)
    assert off.flags & F.HOST_TIMEOUT and not off.flags & F.LEASE_EXPIRED
    # in device time: the host timeout after that PING, to within a telemetry period and a tick
    assert off.t_ms - tel.items[before - 1].t_ms >= 1e3 * HOST_TIMEOUT_S
    assert off.t_ms - tel.items[after].t_ms <= 1e3 * HOST_TIMEOUT_S + TELEMETRY_MS + 2
    wait_until(lambda: sim.state()["current_a"] == 0.0, WAIT_S, "no current in the simulator")
    cs.pause_keepalive(False)
    cs.enable(True)
    tel.wait(lambda t: t.enabled and not t.flags & F.HOST_TIMEOUT)


def test_bad_crc_frames_counted(cs, tel):
    t0 = tel.wait()
    bad = bytearray(p.encode_frame(200, p.MsgType.ENABLE, b"\x01"))
    bad[-2] ^= 0x40
    for _ in range(4):
        cs.send_raw(bytes(bad))
    cs.send_raw(b"\x02\x00")  # a too-short frame
    t = tel.wait(
        lambda t: t.crc_errors >= t0.crc_errors + 4 and t.frame_errors >= t0.frame_errors + 1
    )
    assert (t.crc_errors, t.frame_errors) == (t0.crc_errors + 4, t0.frame_errors + 1)
    assert not t.enabled  # the corrupted ENABLE 1 was dropped
    cs.ping()
    assert cs.link_ok


def test_open_wire_latches(cs, tel, sim):
    sim.set_resistance(0.44)
    cs.set_current(1.0)
    cs.enable(True)
    tel.wait(lambda t: t.current_a > 0.9)
    sim.send("OPEN")
    t = tel.wait(lambda t: t.flags & F.OPEN_WIRE)
    assert not t.enabled
    assert "open wire" in cs.fault_text()
    with pytest.raises(DeviceFault):
        cs.enable(True)
    assert cs.make_safe()
    sim.set_resistance(0.5)
    cs.clear_faults()
    tel.wait(lambda t: not t.flags & F.OPEN_WIRE)
    cs.enable(True)
    tel.wait(lambda t: t.enabled and t.current_a > 0.9)


# ------------------------------------------------------------------ safety, device side
@pytest.mark.parametrize("wire_ohm,supply_v", [(0.3, 4.75), (1.0, 4.75), (0.3, 5.5), (1.0, 5.5)])
def test_current_step_across_wires_and_supplies(raw, sim, wire_ohm, supply_v):
    """The loop is the same on any wire of 0.3–1 Ω and any supply of 4.75–5.5 V (the sink
    regulates; the firmware trims): a 0 → 1 A step settles within 5 % in ≤ 15 ms, no overshoot
    beyond 3 %, and the wire carries 1 A ± 5 mA."""
    sim.set_resistance(wire_ohm)
    sim.send(f"V {supply_v}")
    raw.status(*p.set_lease(5.0))
    raw.status(*p.enable(True))
    raw.status(*p.set_current(1.0))
    first = raw.telemetry(lambda t: t.setpoint_a == pytest.approx(1.0))
    rows = [first] + raw.until(lambda t: t.t_ms >= first.t_ms + 100)  # 100 ms of device time
    t0 = rows[0].t_ms - 5  # the setpoint arrived within the 5 ms before the first frame
    last_out = max((t.t_ms - t0 for t in rows if abs(t.current_a - 1.0) > 0.05), default=0)
    assert last_out <= 10, [(t.t_ms - t0, t.current_a) for t in rows[:5]]
    assert max(t.current_a for t in rows) <= 1.03
    assert sim.state()["current_a"] == pytest.approx(1.0, abs=0.005)


def test_lease_expires_while_pings_go_on(cs, tel, sim):
    """The driver's own keepalive PINGs go on; the control loop stops renewing the setpoint:
    the output goes off after the lease, in device time, with LEASE_EXPIRED, not HOST_TIMEOUT.

    The host timeout (0.5 s) is shorter than the lease (1 s): had the PINGs stopped, the host
    timeout would have tripped first. Each PING may come as late as 0.5 s of device time (about
    0.8 s of host time on a loaded machine), so a busy host does not decide the outcome."""
    lease_ms, host_timeout_s = 1000, 0.5
    sim.set_resistance(0.44)
    cs.set_limits(cs.info.hard_limit_a, host_timeout_s)
    cs.set_lease(lease_ms / 1e3)
    cs.set_current(0.8, wait=True)
    tel.wait()
    # ENABLE 1 (after SET_CURRENT) starts the lease: it reaches the device after frame
    # `before - 1` and before frame `after` (which follows its ACK on the wire)
    before = tel.mark()
    cs.enable(True)
    after = tel.mark()
    k0 = cs.counters().keepalives
    i_on, _ = tel.find(lambda t: t.enabled and t.current_a > 0.75, after)
    i_off, off = tel.find(lambda t: not t.enabled, after)
    assert i_on < i_off, "the output never carried the current"
    assert off.flags & F.LEASE_EXPIRED and not off.flags & F.HOST_TIMEOUT
    assert off.setpoint_a == 0.0
    assert cs.counters().keepalives > k0  # PINGs kept the link alive meanwhile
    assert off.t_ms - tel.items[before - 1].t_ms >= lease_ms
    assert off.t_ms - tel.items[after].t_ms <= lease_ms + TELEMETRY_MS + 2
    wait_until(lambda: sim.state()["current_a"] == 0.0, WAIT_S, "no current in the simulator")
    assert cs.link_ok
    cs.enable(True)  # ENABLE clears the event; SET_CURRENT renews
    cs.set_current(0.5)
    tel.wait(lambda t: t.enabled and not t.flags & F.LEASE_EXPIRED)


def test_estop_input_latches(raw, sim):
    sim.set_resistance(0.44)
    raw.status(*p.set_lease(5.0))
    raw.status(*p.set_current(1.0))
    raw.status(*p.enable(True))
    on = raw.telemetry(lambda t: t.current_a > 0.95)
    sim.send("ESTOP 1")
    off = raw.telemetry(lambda t: t.flags & F.ESTOP)
    # (how fast: within one tick, host tests; here the host's own latency would be in the figure)
    assert not off.enabled and off.t_ms > on.t_ms
    assert sim.state()["current_a"] == 0.0
    assert raw.status(*p.enable(True)) == S.FAULT_ACTIVE
    assert raw.status(*p.clear_faults()) == S.FAULT_ACTIVE  # still tripped
    sim.send("ESTOP 0")
    assert raw.telemetry(lambda t: t.t_ms > off.t_ms + 20).flags & F.ESTOP  # latched
    assert raw.status(*p.clear_faults()) == S.OK
    assert raw.status(*p.enable(True)) == S.OK
    raw.telemetry(lambda t: t.current_a > 0.95)


def test_energy_budget_trips_under_endless_2_5_a(raw, sim):
    """2.5 A demanded for ever: with a budget 16.8× shortened (2 mJ/K for 33.6 mJ/K) 3.6 s stand
    for the 60 s of the real wire. The device trips first and keeps tripping; a wire kinder than
    the model (20 % more heat capacity, h = 120 instead of 90 W/m²K) never reaches 180 °C."""
    sim.set_resistance(0.44)
    short = p.HeatModel(heat_capacity_j_per_k=0.002)
    assert raw.status(*p.set_heat_model(short)) == S.OK
    ack = raw.command(*p.get_heat_model())
    assert p.HeatModel.from_data(ack.data) == short
    raw.telemetry(lambda t: t.wire_model_c < 23.0)  # from ambient, as the wire
    raw.status(*p.set_lease(5.0))
    raw.status(*p.set_current(2.5))
    raw.status(*p.enable(True))
    c_wire, g_wire = 0.002 * 1.2, short.conductance_w_per_k * 120 / 90
    t_wire, peak, first_trip, start, last = 22.0, 22.0, None, None, None
    deadline, last_cmd = time.monotonic() + 60.0, 0.0  # a host bound; the run is device time
    while start is None or last - start < 3600:
        assert time.monotonic() < deadline, "3.6 s of device time did not pass"
        if time.monotonic() - last_cmd > 0.05:  # the host insists, and renews the lease
            for cmd in (p.set_current(2.5), p.clear_faults(), p.enable(True)):
                raw.send(*cmd)
            last_cmd = time.monotonic()
        pkt = raw._next(0.01)
        if pkt is None or pkt.type != M.TELEMETRY:
            continue
        t = p.Telemetry.from_payload(pkt.payload)
        if last is not None:
            dt_s = (t.t_ms - last) / 1e3
            t_wire += (t.current_a**2 * 0.44 - g_wire * (t_wire - 22.0)) * dt_s / c_wire
            peak = max(peak, t_wire)
        if start is None and not t.enabled:
            continue  # frames from before the output came on
        start = t.t_ms if start is None else start
        last = t.t_ms
        if first_trip is None and t.flags & F.OVERTEMP:
            first_trip = t.t_ms - start
            assert t.wire_model_c >= 179.0
    print(f"\nenergy budget (shortened 16.8x): first trip {first_trip} ms into 2.5 A; wire peak "
          f"{peak:.1f} °C over {(last - start) / 1e3:.1f} s of device time")
    # the model: 2 mJ/K × 158 K / ((2.5 A)² × 0.55 Ω) = 92 ms from 22 °C
    assert first_trip is not None and 50 <= first_trip <= 200
    assert peak < 180.0
    raw.status(*p.enable(False))
    raw.status(*p.set_heat_model(p.HeatModel()))


@pytest.mark.parametrize("fault", ["OPEN", "SHORT"])
def test_ntc_open_or_short_is_a_fault(raw, sim, fault):
    assert raw.telemetry(lambda t: not math.isnan(t.ambient_c)).ambient_c == pytest.approx(
        22.0, abs=0.5
    )
    sim.send(f"NTC {fault}")
    t = raw.telemetry(lambda t: t.flags & F.NTC_FAULT)
    assert math.isnan(t.ambient_c)  # never −92 °C or +562 °C
    sim.send("NTC OK")
    raw.telemetry(lambda t: not t.flags & F.NTC_FAULT)


def test_thermocouple_reads_and_faults(raw, sim):
    assert raw.telemetry().thermocouple_status == p.TcStatus.ABSENT  # no chip by default
    sim.send("TC 87.25")
    t = raw.telemetry(lambda t: t.thermocouple_c == 87.25)
    assert t.temperature_c == 87.25 and not t.flags & F.TC_FAULT
    for name, bit in (("OC", p.TcStatus.OC), ("SCG", p.TcStatus.SCG), ("SCV", p.TcStatus.SCV)):
        sim.send(f"TC {name}")
        t = raw.telemetry(lambda t, b=bit: t.thermocouple_status == b)
        assert math.isnan(t.thermocouple_c) and t.flags & F.TC_FAULT
    sim.send("TC NONE")
    t = raw.telemetry(lambda t: t.thermocouple_status == p.TcStatus.ABSENT)
    assert math.isnan(t.thermocouple_c) and not t.flags & F.TC_FAULT
    # a measured wire at the maximum trips OVERTEMP even with a cool model
    raw.status(*p.set_lease(5.0))
    raw.status(*p.set_current(0.3))
    raw.status(*p.enable(True))
    sim.send("TC 181")
    t = raw.telemetry(lambda t: t.flags & F.OVERTEMP)
    assert not t.enabled and t.wire_model_c < 60.0
    assert raw.status(*p.clear_faults()) == S.FAULT_ACTIVE
    sim.send("TC 60")
    raw.telemetry(lambda t: t.thermocouple_c == 60.0)
    assert raw.status(*p.clear_faults()) == S.OK


def test_calibration_in_eeprom(raw, sim):
    """Calibration set and read back; it scales what the firmware reports and regulates."""
    sim.set_resistance(0.44)
    cal = p.Calibration(current_offset_a=0.0, current_gain=1.02, voltage_gain=0.99)
    assert raw.status(*p.set_calibration(cal)) == S.OK
    back = p.Calibration.from_data(raw.command(*p.get_calibration()).data)
    assert back.current_gain == pytest.approx(1.02, abs=1 / 32768)
    assert back.voltage_gain == pytest.approx(0.99, abs=1 / 32768)
    assert back.current_offset_a == 0.0
    raw.status(*p.set_lease(5.0))
    raw.status(*p.set_current(1.0))
    raw.status(*p.enable(True))
    assert raw.status(*p.set_calibration(p.Calibration())) == S.OUTPUT_ON
    # steady in device time (the trim has learned the path): the last 100 ms of 300 ms at 1 A
    on = raw.telemetry(lambda t: t.enabled and t.setpoint_a == pytest.approx(1.0))
    rows = raw.until(lambda t: t.t_ms >= on.t_ms + 300)
    steady = [r.current_a for r in rows if r.t_ms >= on.t_ms + 200]
    assert max(abs(i - 1.0) for i in steady) < 0.003, steady
    t = rows[-1]
    # the firmware believes 1.02 x what the sink gives: the wire carries 1/1.02 A
    assert sim.state()["current_a"] == pytest.approx(1.0 / 1.02, abs=0.005)
    assert t.voltage_v == pytest.approx(0.99 * 0.44 * sim.state()["current_a"], rel=0.003)
    raw.status(*p.enable(False))
    assert raw.status(*p.set_calibration(p.Calibration())) == S.OK


WDT_ELF = REPO / "firmware/build/sim/wdt-hang.elf"
OPTIBOOT = REPO / "firmware/build/boot/optiboot_atmega328.hex"


@pytest.mark.skipif(
    not (WDT_ELF.is_file() and OPTIBOOT.is_file()),
    reason="needs `make -C firmware sim-test` (wdt-hang.elf) and optiboot (make -C firmware sim)",
)
def test_watchdog_reset_reported_behind_optiboot():
    """optiboot clears MCUSR before it starts the application, and leaves its own wait through a
    watchdog reset. The application must report WATCHDOG_RESET after its own hang (the marker its
    watchdog interrupt wrote) and not after optiboot's exit (no marker). Each step waits for the
    event that makes the next one valid (the harness reports every reset), nothing is retried."""
    sim = Harness("--bootloader", str(OPTIBOOT), str(WDT_ELF))
    try:
        mark = len(sim.stderr)
        dev = RawDevice(sim.port_name)  # opening the port resets into optiboot (the auto-reset)
        opened_ms = sim.state()["t_ms"]
        # optiboot's exit: its watchdog reset starts the application
        exit_line = sim.wait_stderr("watchdog", mark)
        mark = exit_line + 1
        app_ms = sim.state()["t_ms"]
        sim.wait_ready_after_reset(exit_line)
        assert dev.status(*p.identify()) == S.OK
        assert dev.status(*p.set_telemetry(0.01)) == S.OK
        first = dev.telemetry(timeout_s=WAIT_S)
        assert not first.flags & F.WATCHDOG_RESET  # optiboot's own watchdog exit is not ours
        # the test build hangs 300 ms after it started: its watchdog interrupt, then the reset;
        # after a watchdog reset optiboot starts the application at once (telemetry off again)
        sim.wait_ready_after_reset(sim.wait_stderr("watchdog", mark))
        assert dev.status(*p.set_telemetry(0.01)) == S.OK
        after = dev.telemetry(timeout_s=WAIT_S)
        assert after.flags & F.WATCHDOG_RESET, after
        assert after.t_ms < first.t_ms + 2000  # device time restarted with the reset
        print(f"\nport opened at {opened_ms:.0f} ms, the application answered from "
              f"{app_ms:.0f} ms (AVR time): {app_ms - opened_ms:.0f} ms of bootloader")
        assert app_ms - opened_ms <= p.READY_AFTER_OPEN_S * 1e3
        dev.close()
    finally:
        sim.close()
