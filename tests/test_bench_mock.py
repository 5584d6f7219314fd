"""Real sessions against the mock bench in its own process, over the real transports.

`smabench mock` serves the plant over a pty (current driver) and Modbus TCP/RTU (sensor);
`smabench run --mock` or the runtime in this process drives it. The mock runs 10× faster than
real time in the loop tests (device time is recorded), in real time in the fault tests.
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
from smabench.bench.runtime import FLAG_SENSOR_INVALID
from smabench.bench.session_run import RunSettings, run_session
from smabench.physics.plant import simulate_plant
from smabench.protocols import ProtocolSettings
from smabench.sessions import load_session

SPEED = 10
PROTOCOL_ARGS = {
    "cycles": ["--cycles", "2", "--heat-s", "3"],
    "incomplete": ["--cycles", "3", "--heat-s", "3", "--partial-cool-s", "2"],
    "inner": ["--cycles", "5", "--heat-s", "3", "--inner-heat-s", "0.4", "--inner-cool-s", "0.8"],
}
LOADS_KG = (1.0, 4.0)


def _run_args(out: Path, sid: str, load_kg: float, protocol: str, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "smabench.cli", "run", "--mock", "--mock-speed", str(SPEED),
        "--load-kg", str(load_kg), "--protocol", protocol, "--current-a", "1.4",
        "--out", str(out), "--session-id", sid, "--quiet", *PROTOCOL_ARGS[protocol], *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[tuple[str, float], Path]:
    """Every protocol at 1 kg and 4 kg, two runs at a time (each with its own mock)."""
    out = tmp_path_factory.mktemp("sessions")
    folders = {}
    for protocol in PROTOCOL_ARGS:
        procs = []
        for load in LOADS_KG:
            sid = f"{protocol}-{load:g}kg"
            extra = ["--mock-sensor", "rtu"] if protocol == "incomplete" else []
            args = _run_args(out, sid, load, protocol, *extra)
            procs.append((load, subprocess.Popen(args, stdout=subprocess.PIPE,
                                                 stderr=subprocess.PIPE, text=True)))  # fmt: skip
        for load, proc in procs:
            stdout, stderr = proc.communicate(timeout=120)
            assert proc.returncode == 0, f"{protocol} {load} kg: {stdout}\n{stderr}"
            assert "completed: protocol completed" in stdout
            folders[(protocol, load)] = out / f"{protocol}-{load:g}kg"
    return folders


def _loop(folder: Path):
    s = load_session(folder)
    d = s.data
    assert s.meta["status"] == "completed" and s.meta["load_kg"] in LOADS_KG
    ok = np.isfinite(d["position_mm"])
    return s, d["t_s"][ok], d["temperature_est_C"][ok], d["position_mm"][ok], d["current_A"][ok]


def _cold_hot_positions(temp_c, pos_mm) -> tuple[float, float]:
    cold = np.median(pos_mm[temp_c < np.percentile(temp_c, 5)])
    hot = np.median(pos_mm[temp_c > np.percentile(temp_c, 95)])
    return float(cold), float(hot)


def _width_k(temp_c, pos_mm) -> float:
    """Loop width: enclosed area / stroke, K (the mean horizontal gap between the branches)."""
    area = abs(float(np.sum(0.5 * (pos_mm[1:] + pos_mm[:-1]) * np.diff(temp_c))))
    cold, hot = _cold_hot_positions(temp_c, pos_mm)
    return area / abs(cold - hot)


def test_complete_cycles_shift_and_narrow_with_load(recorded):
    widths, colds = {}, {}
    for load in LOADS_KG:
        s, t, temp, pos, cur = _loop(recorded[("cycles", load)])
        assert s.data["cycle"].max() == 1  # two cycles
        assert np.nanmax(s.data["current_A"]) == pytest.approx(1.4, abs=0.02)
        # one complete loop: the last cycle, from its heat-up on
        last = s.data["cycle"][np.isfinite(s.data["position_mm"])] == 1
        cold, hot = _cold_hot_positions(temp[last], pos[last])
        assert cold - hot > 2.0  # the full stroke of the 55 mm wire, mm
        widths[load], colds[load] = _width_k(temp[last], pos[last]), cold
    print(f"\nloop width {widths} K; cold-end position {colds} mm")
    assert colds[4.0] > colds[1.0] + 0.2  # heavier load: the loop moves up (longer wire)
    assert widths[4.0] < widths[1.0] - 2.0  # … and gets narrower


def test_recorded_positions_follow_the_plant(recorded):
    """The plant simulated offline on the recorded current reproduces the recorded positions."""
    for load in LOADS_KG:
        _, t, _, pos, cur = _loop(recorded[("cycles", load)])
        trace = simulate_plant(t, np.nan_to_num(cur), load_kg=load, noise_mm=0.0)
        err = trace.position_mm - pos
        stroke = np.ptp(pos)
        rms_percent = 100 * np.sqrt(np.mean(err**2)) / stroke
        assert rms_percent < 6.0, f"{load} kg: {rms_percent:.2f} % of stroke"


def test_incomplete_cycles_reheat_before_cooled(recorded):
    s, t, temp, pos, _ = _loop(recorded[("incomplete", 1.0)])
    cycle = s.data["cycle"][np.isfinite(s.data["position_mm"])]
    cold_full, hot = _cold_hot_positions(temp, pos)
    # cycles 0 and 1 end by reheating after 2 s: the wire had not stretched back yet
    for k in (0, 1):
        end_pos = pos[cycle == k][-1]
        assert end_pos < cold_full - 0.1 * (cold_full - hot), (k, end_pos)
    assert s.meta["devices"]["sensor"]["spec"].startswith("rtu:")


def test_inner_loops_stay_inside_the_major_loop(recorded):
    s, t, temp, pos, _ = _loop(recorded[("inner", 4.0)])
    cycle = s.data["cycle"][np.isfinite(s.data["position_mm"])]
    stroke = np.ptp(pos)
    inner = (cycle >= 1) & (cycle <= 3)
    assert np.ptp(pos[inner]) < 0.8 * stroke  # partial transformations only
    assert np.ptp(temp[inner]) < 0.8 * np.ptp(temp)


# ----------------------------------------------------------------------------- faults
def _settings(tmp_path: Path, sid: str, **proto) -> RunSettings:
    return RunSettings(
        load_kg=2.0,
        protocol=ProtocolSettings(name="cycles", cycles=50, current_a=0.8, **proto),
        out_dir=tmp_path,
        session_id=sid,
    )


def test_killed_mock_ends_session_within_half_a_second(tmp_path):
    settings = _settings(tmp_path, "killed-mock")
    with MockProcess(["--load-kg", "2"]) as mock:
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        out: dict = {}

        def run() -> None:
            out["folder"], out["result"] = run_session(settings, source, sensor)

        runner = threading.Thread(target=run)
        runner.start()
        time.sleep(1.0)  # let it run: the kill must come mid-session
        t_kill = time.monotonic()
        mock.kill()
        runner.join(5.0)
        noticed_s = time.monotonic() - t_kill
        source.close()
        sensor.close()
    result = out["result"]
    print(f"\nmock killed: session ended {noticed_s * 1e3:.0f} ms later ({result.reason})")
    assert result.status == "aborted"
    assert "lost" in result.reason
    assert noticed_s < 0.5
    s = load_session(out["folder"])
    assert s.meta["status"] == "aborted" and s.meta["end_reason"] == result.reason
    assert len(s) == result.samples > 100


def test_modbus_timeout_burst_is_flagged_and_run_continues(tmp_path):
    settings = _settings(tmp_path, "burst", heat_s=0.5, min_cool_s=0.5, cool_timeout_s=1.0)
    settings.protocol.cycles = 2
    with MockProcess(["--load-kg", "2"]) as mock:
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        runner = threading.Thread(target=run_session, args=(settings, source, sensor))
        runner.start()
        time.sleep(0.5)
        mock.send("sensor-delay 0.08 8")  # 8 responses later than the 50 ms request timeout
        runner.join(30.0)
        source.close()
        sensor.close()
    s = load_session(tmp_path / "burst")
    assert s.meta["status"] == "completed", s.meta["end_reason"]
    flagged = (s.data["flags"].astype(int) & FLAG_SENSOR_INVALID) != 0
    assert 4 <= flagged.sum() <= 8
    assert np.all(np.isnan(s.data["position_mm"][flagged]))
    assert np.all(np.isfinite(s.data["position_mm"][~flagged]))


def test_kill_9_of_run_leaves_readable_rows_up_to_one_second_before(tmp_path):
    args = [
        sys.executable, "-m", "smabench.cli", "run", "--mock", "--load-kg", "2",
        "--cycles", "20", "--current-a", "0.8", "--out", str(tmp_path), "--session-id", "k9",
    ]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    progress: list[tuple[float, float]] = []  # (run time t_s, wall time the line arrived)
    for line in proc.stdout:
        if line.strip().startswith("t "):
            progress.append((float(line.split()[1]), time.monotonic()))
            if progress[-1][0] >= 3.0:
                break
    time.sleep(0.37)  # mid-way between two flushes
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
    """`--mock-firmware emulated`: the AVR build drives the plant through the harness."""
    from smabench.drivers.mock.bench import SIM_BIN, SIM_ELF

    if not (SIM_BIN.is_file() and SIM_ELF.is_file()) and not os.environ.get("CI"):
        pytest.skip("firmware build missing (`make -C firmware elf sim`)")
    proc = subprocess.run(
        [sys.executable, "-m", "smabench.cli", "run", "--mock", "--mock-firmware", "emulated",
         "--load-kg", "2", "--cycles", "1", "--current-a", "1.4", "--heat-s", "3",
         "--cool-timeout-s", "2", "--out", str(tmp_path), "--session-id", "emu", "--quiet"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    s = load_session(tmp_path / "emu")
    d = s.data
    heat = d["current_set_A"] > 0
    # the firmware's PI loop holds the measured current at the setpoint once it has settled
    settled = heat & (d["t_s"] > d["t_s"][heat][0] + 0.2)
    assert np.median(d["current_A"][settled]) == pytest.approx(1.4, abs=0.03)
    assert np.nanmax(d["position_mm"]) - np.nanmin(d["position_mm"]) > 2.0  # it contracted
    assert s.meta["devices"]["current_driver"]["name"] == "SMA-CD328"


def test_link_and_loop_benchmarks_print_figures(run_cli):
    """Short runs of the benchmarks (the figures in the README come from full-length runs)."""
    link = run_cli("bench", "link", "--firmware", "python", "-n", "20", "--telemetry-s", "0.5",
                   check=True)  # fmt: skip
    assert "PING         round trip: median" in link.stdout
    assert "Modbus TCP: read latency" in link.stdout
    loop = run_cli("bench", "loop", "--duration-s", "1", "--rates", "200", "--firmware", "python",
                   check=True)  # fmt: skip
    row = [line for line in loop.stdout.splitlines() if line.strip().startswith("200 python")]
    assert row and 190 < float(row[0].split()[5]) < 210  # achieved Hz
