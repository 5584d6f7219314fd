"""Real sessions against the mock bench in its own process, over the real transports.

`smabench mock` serves the plant over a pty (current driver) and Modbus TCP/RTU (sensor);
`smabench run --mock` or the runtime in this process drives it. These tests check behaviour
that needs real processes and transports — a session recorded end to end, a killed mock, a
Modbus timeout burst, a killed run, bad settings, the real firmware in simavr — with margins
that hold on a busy machine, measured on what the devices did (the telemetry's measured current,
the rows on disk). Accuracy and physics (loops against load, incomplete and inner cycles, the
plant following the recorded current) are tested on simulated time in-process
(``tests/test_runtime.py``), where a busy machine cannot change them.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from smabench.bench.headless import MockProcess, open_devices
from smabench.bench.session_run import RunSettings, run_session
from smabench.protocols import ProtocolSettings
from smabench.sessions import FLAG_SENSOR_INVALID, load_session

# real processes and transports: seconds each
pytestmark = [pytest.mark.slow, pytest.mark.realtime_bench]

RATE_HZ = 50.0
"""Loop rate of these sessions: what they test does not need the bench's 200 Hz, and a quarter
of the traffic leaves a busy machine more room (the loop's timing is `smabench bench loop`'s)."""


def test_run_records_a_session_end_to_end_over_the_real_transports(tmp_path):
    """`smabench run --mock` (the sensor over Modbus RTU): a completed session whose rows show
    the driver's measured current at the setpoint and the wire contracting."""
    proc = subprocess.run(
        [sys.executable, "-m", "smabench.cli", "run", "--mock", "--mock-sensor", "rtu",
         "--rate-hz", str(RATE_HZ), "--load-kg", "2", "--cycles", "1", "--heat-s", "4",
         "--cool-timeout-s", "1",
         "--current-a", "1.6", "--out", str(tmp_path),
         "--session-id", "e2e", "--quiet"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "completed: protocol completed" in proc.stdout
    s = load_session(tmp_path / "e2e")
    d = s.data
    assert s.meta["status"] == "completed" and s.meta["load_kg"] == 2.0
    assert s.meta["devices"]["sensor"]["spec"].startswith("rtu:")
    assert np.all(np.diff(d["t_s"]) > 0)
    heat = d["current_set_A"] > 0
    # device side: the driver measured the setpoint once it settled (its telemetry)
    settled = heat & (d["t_s"] > d["t_s"][heat][0] + 0.2)
    assert np.median(d["current_A"][settled]) == pytest.approx(1.6, abs=0.02)
    pos = d["position_mm"][np.isfinite(d["position_mm"])]
    assert pos[0] - np.min(pos) > 1.5  # the wire contracted (2.6 mm full stroke at 2 kg)


# ----------------------------------------------------------------------------- faults
def _settings(tmp_path: Path, sid: str, **proto) -> RunSettings:
    return RunSettings(
        load_kg=2.0,
        protocol=ProtocolSettings(name="cycles", cycles=50, current_a=0.8, **proto),
        rate_hz=RATE_HZ,
        out_dir=tmp_path,
        session_id=sid,
    )


class _Session:
    """``run_session`` on its own thread, as every caller has it (its loop real-time where
    allowed: run_session's own); :meth:`wait_rows` waits until it has recorded rows.
    ``on_sample`` is called with every row too."""

    def __init__(self, settings: RunSettings, source, sensor, devices=None, on_sample=None):
        self.rows = 0
        self.enough = threading.Event()
        self.need = 0
        self.out: dict = {}
        self._on_row = on_sample
        self.thread = threading.Thread(target=self._run, args=(settings, source, sensor, devices))
        self.thread.start()

    def _on_sample(self, row: dict) -> None:
        if self._on_row is not None:
            self._on_row(row)
        self.rows += 1
        if self.rows >= self.need:
            self.enough.set()

    def _run(self, settings, source, sensor, devices) -> None:
        self.out["policy_before"] = os.sched_getscheduler(0)
        self.out["folder"], self.out["result"] = run_session(
            settings, source, sensor, devices, on_sample=self._on_sample,
        )  # fmt: skip
        self.out["policy_after"] = os.sched_getscheduler(0)

    def result(self, timeout_s: float = 120.0):
        """(folder, result) once the session ended (a generous bound, not a measurement)."""
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), f"session still running after {timeout_s} s"
        return self.out["folder"], self.out["result"]

    def wait_rows(self, n: int, timeout_s: float = 30.0) -> None:
        self.need = n
        if self.rows < n:
            self.enough.clear()
            assert self.enough.wait(timeout_s), f"only {self.rows} rows in {timeout_s} s"


def test_every_callers_loop_runs_real_time_and_is_put_back(tmp_path):
    """run_session with no help from its caller (as `smabench plan` calls it): the loop thread
    is SCHED_FIFO while it runs and as before afterwards. Before, only `run` and the GUI's
    runtime raised it, each on its own; a plan's loop at normal scheduling stalled 0.33 s on
    a busy CI and its step was stopped by the lease."""
    if not _can_be_realtime():
        pytest.skip("no CAP_SYS_NICE: the loop stays at normal scheduling")
    settings = _settings(tmp_path, "realtime")
    seen: list[int] = []
    with MockProcess(["--load-kg", "2"]) as mock:
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        run = _Session(settings, source, sensor,
                       on_sample=lambda row: seen.append(os.sched_getscheduler(0)))  # fmt: skip
        run.wait_rows(20)
        mock.kill()  # the session ends (driver lost)
        run.result(30.0)
        source.close()
        sensor.close()
    assert seen and set(seen[:20]) == {os.SCHED_FIFO}, set(seen)
    assert run.out["policy_before"] == run.out["policy_after"] == os.SCHED_OTHER


def _can_be_realtime() -> bool:
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, policy, param)
    return True


def test_killed_mock_ends_session_within_half_a_second(tmp_path):
    settings = _settings(tmp_path, "killed-mock")
    with MockProcess(["--load-kg", "2"]) as mock:
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        run = _Session(settings, source, sensor)
        run.wait_rows(50)  # mid-session: the kill comes once it is running
        t_kill = time.monotonic()
        mock.kill()
        run.thread.join(10.0)
        noticed_s = time.monotonic() - t_kill
        source.close()
        sensor.close()
    result = run.out["result"]
    print(f"\nmock killed: session ended {noticed_s * 1e3:.0f} ms later ({result.reason})")
    assert result.status == "aborted"
    assert "lost" in result.reason
    assert noticed_s < 0.5  # the link timeout is 0.25 s: the safe state within 0.5 s
    s = load_session(run.out["folder"])
    assert s.meta["status"] == "aborted" and s.meta["end_reason"] == result.reason
    assert len(s) == result.samples >= 50


def test_a_killed_mock_leaves_nothing_in_the_temporary_folder(tmp_path, monkeypatch):
    """SIGKILL gives the mock no clean-up (the faults tests pull benches this way): what it made
    in the temporary folder, the RTU pty pair's links and its copy of the firmware's core, goes
    without it. socat, which ends with its parent, removes its links; a folder around them
    stayed behind (356 ``smabench-mock-*`` folders in /tmp here)."""
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    with MockProcess(["--load-kg", "2"]) as mock:
        assert str(tmp_path) in (mock.ports.sensor_rtu or ""), mock.ports
        mock.kill()
    deadline = time.monotonic() + 10.0
    while list(tmp_path.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.05)  # socat ends on its parent's death: polling that, not a fixed wait
    assert list(tmp_path.iterdir()) == []


def test_modbus_timeout_burst_is_flagged_and_run_continues(tmp_path):
    """Late Modbus answers (the mock delays 8 responses by 80 ms, past the 50 ms request
    timeout) come back as flagged rows with no position; the session goes on. The exact count
    of flagged rows is tested on simulated time (test_runtime.py): here, on a busy machine,
    other reads may time out too."""
    settings = _settings(tmp_path, "burst", heat_s=0.5, min_cool_s=0.5, cool_timeout_s=1.0)
    settings.protocol.cycles = 2
    with MockProcess(["--load-kg", "2"]) as mock:
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        run = _Session(settings, source, sensor)
        run.wait_rows(25)
        mock.send("sensor-delay 0.08 8")
        run.thread.join(60.0)
        source.close()
        sensor.close()
    s = load_session(tmp_path / "burst")
    assert s.meta["status"] == "completed", s.meta["end_reason"]
    flagged = (s.data["flags"].astype(int) & FLAG_SENSOR_INVALID) != 0
    assert flagged.sum() >= 4, flagged.sum()
    assert np.all(np.isnan(s.data["position_mm"][flagged]))
    assert np.all(np.isfinite(s.data["position_mm"][~flagged]))


def test_kill_9_of_run_leaves_readable_rows_up_to_one_second_before(tmp_path):
    args = [
        sys.executable, "-m", "smabench.cli", "run", "--mock", "--load-kg", "2",
        "--rate-hz", str(RATE_HZ), "--cycles", "20", "--current-a", "0.8", "--out",
        str(tmp_path), "--session-id", "k9",
    ]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    progress: list[tuple[float, float]] = []  # (run time t_s, wall time the line arrived)
    for line in proc.stdout:
        if line.strip().startswith("t "):
            progress.append((float(line.split()[1]), time.monotonic()))
            if progress[-1][0] >= 3.0:
                break
    t_kill = time.monotonic()
    proc.kill()
    proc.wait()
    t_run, wall = progress[-1]
    run_time_at_kill = t_run + (t_kill - wall)
    s = load_session(tmp_path / "k9")
    assert s.meta["status"] == "running"  # it never got to write its end
    last = float(s.data["t_s"][-1])
    print(f"\nkill -9 at run time {run_time_at_kill:.2f} s: rows on disk up to {last:.2f} s")
    assert last >= run_time_at_kill - 1.0
    assert np.all(np.diff(s.data["t_s"]) > 0)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--load-kg", "-1"], "load must be"),
        (["--load-kg", "2", "--current-a", "2.4"], "outside 0"),
        (["--load-kg", "2", "--protocol", "sawtooth"], "unknown protocol"),
        (["--load-kg", "2", "--rate-hz", "0"], "loop rate"),
    ],
)
def test_bad_settings_rejected_before_any_device_opens(tmp_path, args, message):
    # a port that does not exist: reaching it would be a different error
    proc = subprocess.run(
        [sys.executable, "-m", "smabench.cli", "run", "--port", "/nonexistent/tty",
         "--sensor", "tcp:127.0.0.1:1", "--out", str(tmp_path), *args],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert proc.returncode == 2
    assert message in proc.stderr
    assert "nonexistent" not in proc.stderr
    assert not any(tmp_path.iterdir())  # no session folder either


@pytest.mark.emulator
def test_session_with_the_real_firmware_in_simavr(tmp_path):
    """The AVR build in simavr drives the plant through the harness during a recorded session.

    Checked on the device side, so it holds however fast simavr runs on a busy machine (the
    host's heating phase is wall time, the plant's is the AVR's): the plant receives the
    setpoint, and its temperature at the end of heating is what the heat balance gives for
    that current over the AVR time that passed."""
    from smabench.drivers.mock.bench import SIM_BIN, SIM_ELF, MockBench
    from smabench.physics.thermal import step_exact

    if not (SIM_BIN.is_file() and SIM_ELF.is_file()):
        if os.environ.get("CI"):
            pytest.fail("firmware build missing under CI (`make -C firmware elf sim`)")
        pytest.skip("firmware build missing (`make -C firmware elf sim`)")
    settings = RunSettings(
        load_kg=2.0,
        protocol=ProtocolSettings(name="cycles", cycles=1, current_a=1.4, heat_s=3.0,
                                  cool_timeout_s=1.0),  # fmt: skip
        out_dir=tmp_path,
        session_id="emu",
        rate_hz=RATE_HZ,
    )
    seen: dict[str, tuple[float, float, float]] = {}  # phase → (AVR s, plant °C, plant A)

    with MockBench(2.0, firmware="emulated", rtu=False, realtime=True) as bench:
        plant = bench.link.plant

        def on_sample(row: dict) -> None:
            if row["current_set_A"] > 0:
                state = bench.link.state
                seen.setdefault("heat_start", (plant.t_s, state.temperature_c, state.current_a))
                seen["heat_end"] = (plant.t_s, state.temperature_c, state.current_a)

        source, sensor = open_devices(bench.ports.driver, bench.ports.sensor_tcp, settings)
        try:
            folder, result = _Session(
                settings, source, sensor, {"current_driver": {"name": source.info.name}},
                on_sample=on_sample,
            ).result()  # fmt: skip
        finally:
            source.close()
            sensor.close()
    assert result.status == "completed", result.reason
    d = load_session(folder).data
    heat = d["current_set_A"] > 0
    settled = heat & (d["t_s"] > d["t_s"][heat][0] + 0.2)
    # the firmware holds its measured current at the setpoint (its telemetry)
    assert np.median(d["current_A"][settled]) == pytest.approx(1.4, abs=0.03)
    t0, temp0, _ = seen["heat_start"]
    t1, temp1, current = seen["heat_end"]
    assert current == pytest.approx(1.4, abs=0.05)  # what the plant received
    assert t1 - t0 > 0.3  # the AVR ran (its share of the 3 s of wall time)
    expected = step_exact(temp0, 1.4, t1 - t0, bench.link.plant.p.wire)
    print(f"\nsimavr: {t1 - t0:.2f} s of AVR time in 3 s of heating; wire {temp0:.1f} → "
          f"{temp1:.1f} °C, heat balance {expected:.1f} °C")
    assert temp1 - temp0 == pytest.approx(expected - temp0, rel=0.1)


@pytest.mark.emulator
def test_realtime_harness_is_cpu_favoured_but_never_fifo():
    """The simavr harness computes about 85 % of a core without sleeping: at SCHED_FIFO it
    starved the pty's kernel worker and the host's threads on its core (5 of 6 emulated sessions
    aborted beside a second harness and a CPU-bound process). Favoured by nice, where allowed."""
    from smabench.drivers.mock.bench import HARNESS_NICE, SIM_BIN, SIM_ELF, MockBench

    if not (SIM_BIN.is_file() and SIM_ELF.is_file()):
        pytest.skip("firmware build missing (`make -C firmware elf sim`)")
    with MockBench(2.0, firmware="emulated", rtu=False, realtime=True) as bench:
        pid = bench.emulated.proc.pid
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        if os.geteuid() == 0:
            assert os.getpriority(os.PRIO_PROCESS, pid) == HARNESS_NICE


def test_link_and_loop_benchmarks_print_figures(run_cli):
    """Short runs of the benchmarks (the figures in the README come from full-length runs)."""
    link = run_cli("bench", "link", "--firmware", "python", "-n", "20", "--telemetry-s", "0.5",
                   check=True)  # fmt: skip
    assert any(line.strip().startswith("PING") and "median" in line
               for line in link.stdout.splitlines()), link.stdout  # fmt: skip
    assert "Modbus TCP: read latency" in link.stdout
    assert "no response in time: " in link.stdout
    loop = run_cli("bench", "loop", "--duration-s", "1", "--rates", "50", "--firmware", "python",
                   check=True)  # fmt: skip
    row = [line for line in loop.stdout.splitlines() if line.strip().startswith("50 python")]
    assert row, loop.stdout
    # …, ticks, achieved Hz, jitter p50/p99/max ms, missed: figures, not a speed assertion
    # (how fast the loop runs depends on the machine)
    ticks, achieved_hz = int(row[0].split()[-6]), float(row[0].split()[-5])
    assert ticks > 10 and 0.0 < achieved_hz <= 1.5 * 50


def test_modbus_latency_counts_reads_that_got_no_answer(monkeypatch):
    """On a loaded machine the mock sensor can miss its 0.1 s: the benchmark counts such reads
    (a figure) instead of ending; it still fails when nothing is answered."""
    from smabench.bench import link_bench
    from smabench.drivers.base import SensorTimeout

    class Sample:
        ok, error = True, ""

    class Sensor:
        def __init__(self, answers):
            self.answers = iter(answers)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def read(self):
            if next(self.answers):
                return Sample()
            raise SensorTimeout("rtu:x: no response within 0.1 s")

    answers = [True, True, False, True, False, True]  # warm-up, then 5 timed reads
    monkeypatch.setattr(link_bench, "DisplacementSensor", lambda _m, _s: Sensor(answers))
    out = link_bench.modbus_latency("rtu:x", 5)
    assert out["n"] == 3 and out["no_response"] == 2
    monkeypatch.setattr(link_bench, "DisplacementSensor", lambda _m, _s: Sensor([False] * 6))
    with pytest.raises(RuntimeError, match="none of 5 Modbus reads was answered"):
        link_bench.modbus_latency("rtu:x", 5)


def test_the_mock_drivers_wire_voltage_gets_the_asked_noise():
    """``smabench mock --wire-noise-v V``: Gaussian noise of the wire-voltage channel, V RMS at
    the wire, one draw per 1 ms step (as the offline driver draws it), seeded; refused with the
    emulated firmware: tests/test_firmware_emulated.py."""
    from smabench.drivers.mock.bench import MockBench
    from smabench.drivers.mock.firmware import MockFirmware

    fw = MockFirmware(0.0)
    draws = {}
    for seed in (3, 3, 4):
        bench = MockBench(2.0, speed=5.0, wire_noise_v=5e-5, seed=seed)
        draws.setdefault(seed, []).append(
            np.array([bench._couple(float(k), 1e-3, fw).wire_offset_v for k in range(4000)])
        )
    a, b = draws[3]
    np.testing.assert_array_equal(a, b)  # seeded
    assert not np.array_equal(a, draws[4][0])
    assert np.std(a) == pytest.approx(5e-5, rel=0.05) and abs(np.mean(a)) < 5e-6
    quiet = MockBench(2.0, speed=5.0)
    assert quiet._couple(1.0, 1e-3, fw).wire_offset_v == 0.0
