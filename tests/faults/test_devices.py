"""Device faults: the current driver's link gone (the mock killed: a cable pulled), a second
program opening the driver's port, the sensor returning Modbus exceptions."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from smabench.sessions import FLAG_AFTER_END, FLAG_SENSOR_INVALID, load_session

from .conftest import (
    END_TIMEOUT_S,
    assert_ends_aborted,
    assert_wire_safe,
    command_cwd,
    command_env,
    installed_python,
    rows_on_disk,
    smabench_command,
)

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_driver_link_lost_warns_in_true_words_and_aborts(tmp_path, run_mock):
    run = run_mock(tmp_path, "s")
    run.wait_progress(1.0)
    rows_before = rows_on_disk(run.folder)
    os.kill(run.mock_pid(), signal.SIGKILL)  # the bench gone at once, as a cable pulled out
    rc, out, err = run.finish()
    assert "the session goes on" not in err, err  # it does not: it aborts 0.25 s later
    lines = err.strip().splitlines()
    assert rc == 1 and "Traceback" not in err, err
    assert "telemetry lost" in lines[-1], err
    warned = [ln for ln in lines if "current driver reports link lost" in ln]
    assert warned and all("the session aborts unless telemetry returns within 0.25 s" in ln
                          for ln in warned), err  # fmt: skip
    meta = json.loads((run.folder / "session.json").read_text())
    assert meta["status"] == "aborted" and "telemetry lost" in meta["end_reason"], meta
    assert len(load_session(run.folder)) == meta["rows"] >= rows_before


@pytest.mark.slow
def test_a_second_program_on_the_driver_port_is_refused_naming_the_holder(tmp_path, run_mock):
    run = run_mock(tmp_path, "s")
    run.wait_progress(1.0)
    port = json.loads((run.folder / "session.json").read_text())["devices"]["current_driver"][
        "port"
    ]
    second = subprocess.run([*smabench_command(), "calibrate", "show", "--port", port],
                            capture_output=True, text=True, cwd=command_cwd(),
                            env=command_env(), timeout=120)  # fmt: skip
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2, second.stderr
    assert len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
    assert f"in use by pid {run.proc.pid} (" in lines[0] and "run --mock" in lines[0], lines
    t = run.wait_progress(2.5)  # the session went on, undisturbed
    run.signal(signal.SIGINT)
    rc, out, err = run.finish(END_TIMEOUT_S)
    assert_ends_aborted(rc, err, "SIGINT")
    assert t >= 2.5


def _flags(folder) -> np.ndarray:
    return load_session(folder).data["flags"].astype(int)


@pytest.mark.slow
def test_sensor_modbus_exceptions_flag_rows_then_a_silent_sensor_ends_the_session(
    tmp_path, run_mock, mock_bench
):
    trace = tmp_path / "trace.csv"
    bench = mock_bench(trace)
    run = run_mock(tmp_path, "s", devices=bench.devices)
    run.wait_progress(1.0)
    bench.send("sensor-exception 4 20")  # 20 readings answered with "server device failure"
    t = run.wait_progress(2.5)
    flagged = (_flags(run.folder) & FLAG_SENSOR_INVALID) != 0
    assert 15 <= flagged.sum() <= 25, flagged.sum()  # a burst: flagged rows, the session on
    assert t >= 2.5
    bench.send("sensor-exception 4 1000000")  # from now on: the sensor unplugged behind its
    rc, out, err = run.finish()  # RS-485 gateway (every answer an exception)
    assert_ends_aborted(rc, err, "displacement sensor lost for 1.")
    meta = json.loads((run.folder / "session.json").read_text())
    assert meta["status"] == "aborted" and "sensor lost" in meta["end_reason"]
    bench.close()  # its trace closed
    assert_wire_safe(trace)


@pytest.mark.slow
def test_sensor_not_answering_ends_the_session_sensor_lost(tmp_path, run_mock, mock_bench):
    trace = tmp_path / "trace.csv"
    bench = mock_bench(trace)
    run = run_mock(tmp_path, "s", devices=bench.devices)
    run.wait_progress(1.0)
    bench.send("sensor-delay 5 1000000")  # every answer 5 s late: the cable pulled
    rc, out, err = run.finish()
    # pymodbus logs its own "No response received" (the CLI leaves its logger at WARNING)
    assert_ends_aborted(rc, err, "displacement sensor lost for 1.", warnings_from="ERROR pymodbus")
    bench.close()
    assert_wire_safe(trace)


@pytest.mark.slow
def test_sensor_frozen_while_the_wire_transforms_ends_the_session(tmp_path, run_mock, mock_bench):
    trace = tmp_path / "trace.csv"
    bench = mock_bench(trace)
    # 1.6 A takes the wire through its transformation (1 A under 1 kg stays below As: with a
    # frozen reading no one can tell, and the check does not claim to)
    run = run_mock(tmp_path, "s", "--current-a", "1.6", devices=bench.devices)
    run.wait_progress(0.0)  # the first heating has just begun: the wire is still cold
    bench.send("sensor-freeze 1000000")  # valid answers, all the same reading from now on
    rc, out, err = run.finish()
    assert_ends_aborted(rc, err, "displacement sensor frozen: the same reading")
    s = load_session(run.folder)
    meta = s.meta
    assert meta["status"] == "aborted" and "through its transformation" in meta["end_reason"]
    live = (s.data["flags"].astype(int) & FLAG_AFTER_END) == 0  # before the after-end rows
    position = s.data["position_mm"][live]
    frozen_rows = position == position[-1]
    assert frozen_rows.sum() > 50  # it was frozen a while before anything could tell
    assert int(s.data["flags"][live][-1]) & FLAG_SENSOR_INVALID  # the row that told is flagged
    assert abs(s.data["current_A"][-1]) < 0.02  # and the record goes on until the wire is off
    bench.close()
    assert_wire_safe(trace)


STILL_WIRE = """
from smabench.bench.runtime import FrozenSensor

f = FrozenSensor(as_c=68.0, af_c=78.0)
# no current: the wire rests at 25 °C, the sensor repeats its last digit for a minute
assert not any(f.update(0.005 * k, 1.2345, 25.0) for k in range(12_000))
# heating that stays below the transformation: no motion, no alarm
assert not any(f.update(60 + 0.005 * k, 1.2345, 25.0 + k * 0.01) for k in range(4000))
# through the transformation with the same reading: frozen
print(f.update(100.0, 1.2345, 120.0))
"""


def test_a_still_wire_with_a_steady_reading_is_not_taken_for_a_frozen_sensor():
    """The installed package's check (its interpreter), fed a still wire's readings."""
    proc = subprocess.run([str(installed_python()), "-c", STILL_WIRE], capture_output=True,
                          text=True, cwd=command_cwd(), env=command_env(), timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "frozen" in proc.stdout, proc.stdout


REPLUG_CLIENT = """
import os, sys, time
from smabench.drivers.current_source import CurrentSource

source = CurrentSource(sys.argv[1], max_reconnect_attempts=int(sys.argv[3]))
source.connect()
assert source.link_ok
print("connected", flush=True)
# the test unplugs and plugs back, then says so (with the new name when argv[2] is empty)
said = sys.stdin.readline().strip()
new_name = sys.argv[2] or said
deadline = time.monotonic() + 60
while not (source.link_ok and source._link.port_name == new_name):
    assert time.monotonic() < deadline, "not reconnected through the stable name"
    time.sleep(0.05)  # polls the condition
print("pong", source.ping() > 0, flush=True)  # a round trip to the bench behind the name
source.close()
"""


@pytest.mark.slow
def test_driver_replugged_under_another_name_is_found_again_by_its_stable_name(
    tmp_path, mock_bench
):
    """udev's /dev/serial/by-id names an adapter by its serial number whatever ttyUSB it gets:
    the link follows it on a reopen. The link of the installed package (its interpreter, a
    client process such as the GUI's); the replug from outside it: the first bench's pty
    removed (the mock killed), the stable name moved to a second bench's new pty, as udev
    does."""
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    first = mock_bench(tmp_path / "t1.csv")
    second = mock_bench(tmp_path / "t2.csv")
    stable = by_id / "usb-FTDI_FT232R_USB_UART_A10KZ3XY-if00-port0"
    stable.symlink_to(first.driver)
    client = subprocess.Popen(
        [str(installed_python()), "-c", REPLUG_CLIENT, first.driver, second.driver, "20"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        cwd=command_cwd(), env=command_env({"SMABENCH_SERIAL_BY_ID": str(by_id)}),
    )  # fmt: skip
    try:
        assert client.stdout.readline().strip() == "connected", client.stderr.read()
        first.proc.kill()  # unplugged: its pty is gone
        first.proc.wait()
        tmp = by_id / ".new"
        tmp.symlink_to(second.driver)
        os.replace(tmp, stable)  # plugged back: another device name, the same stable name
        out, err = client.communicate("replugged\n", timeout=120)
    finally:
        if client.poll() is None:
            client.kill()
            client.wait()
    assert client.returncode == 0 and out.strip() == "pong True", (out, err)
    assert f"port {first.driver} is now {second.driver} ({stable})" in err, err


def _take_pty_name(name: str, limit_s: float = 15.0) -> list[int]:
    """Open ptys until one gets ``name`` (a pty number freed when its bench died, released by
    the kernel a little after the node goes) or another process has it; returns the fds that
    hold it, or none taken when someone else was first. The kernel hands out the lowest free
    number, so the ptys opened on the way are closed once it is ours."""
    deadline = time.monotonic() + limit_s
    tried: list[tuple[int, int]] = []
    try:
        while time.monotonic() < deadline:
            if os.path.exists(name) and not any(os.ttyname(s) == name for _, s in tried):
                time.sleep(0.05)  # the old bench still holds it: polls the condition
                continue
            master, slave = os.openpty()
            if os.ttyname(slave) == name:
                return [master, slave]
            tried.append((master, slave))
            if os.path.exists(name):  # someone else has it now: the device cannot get it back
                return []
            if len(tried) >= 20:  # not released after 20 tries: leave it (the test says so)
                return []
            time.sleep(0.05)  # not released yet: polls the condition
        return []
    finally:
        for master, slave in tried:
            os.close(master)
            os.close(slave)


@pytest.mark.slow
@pytest.mark.emulator
def test_emulated_driver_replugged_is_found_again_by_its_stable_name(tmp_path, mock_bench):
    """The same replug with the real firmware in simavr behind the pty (``--firmware
    emulated``), as udev does it: the first bench killed (its harness goes with it, its pty is
    gone) and its stable name removed; the old device name taken by another device (a pty of
    the test's own: a second adapter plugged in meanwhile); a second emulated bench started (one
    harness at a time: each takes most of a core) and the stable name created for it. The link
    must wait for the stable name, never open the stranger under the old name."""
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    # the installed package carries no firmware build: the checkout's (make firmware-build)
    builds = {"SMABENCH_SIM": str(REPO / "firmware/build/sim/smabench-sim"),
              "SMABENCH_ELF": str(REPO / "firmware/build/avr/smabench-cd.elf")}  # fmt: skip
    first = mock_bench(tmp_path / "t1.csv", "--firmware", "emulated", env=builds)
    stable = by_id / "usb-FTDI_FT232R_USB_UART_A10KZ3XY-if00-port0"
    stable.symlink_to(first.driver)
    client = subprocess.Popen(  # 60 reopen attempts, ≥ 50 s: an emulated start on a busy host
        [str(installed_python()), "-c", REPLUG_CLIENT, first.driver, "", "60"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        cwd=command_cwd(), env=command_env({"SMABENCH_SERIAL_BY_ID": str(by_id)}),
    )  # fmt: skip
    held = None
    try:
        assert client.stdout.readline().strip() == "connected", client.stderr.read()
        first.proc.kill()  # unplugged: the mock, its harness and its pty are gone
        first.proc.wait()
        stable.unlink()  # udev removes the adapter's names
        held = _take_pty_name(first.driver)  # another device under the old name
        second = mock_bench(tmp_path / "t2.csv", "--firmware", "emulated", env=builds)
        assert second.driver != first.driver
        stable.symlink_to(second.driver)  # plugged back: the same stable name
        client.stdin.write(second.driver + "\n")
        client.stdin.flush()
        out, err = client.communicate(timeout=120)
    finally:
        for fd in held or ():
            os.close(fd)
        if client.poll() is None:
            client.kill()
            client.wait()
    assert client.returncode == 0 and out.strip() == "pong True", (out, err)
    assert f"port {first.driver} is now {second.driver} ({stable})" in err, err
