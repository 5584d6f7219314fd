"""Campaigns: plan validation, dry-run budget, load-change prompt, crash and resume."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from smabench import plan as planmod
from smabench.plan import PlanError, dry_run, execute, load_plan, load_state, new_state
from smabench.sessions import SessionWriter, load_session

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "sessions" / "plans" / "example.toml"

PLAN = """
[plan]
name = "t"
out = "{out}"
mock_speed = 5
[[step]]
name = "a"
protocol = "cycles"
load_kg = 1.0
cycles = 2
current_a = 1.0
heat_s = 2.0
cool_timeout_s = 8.0
rest_s = 4.0
[[step]]
name = "b"
protocol = "cycles"
load_kg = 2.0
cycles = 1
current_a = 1.5
heat_s = 3.0
cool_timeout_s = 10.0
[[step]]
name = "c"
protocol = "inner"
load_kg = 2.0
cycles = 1
current_a = 1.2
heat_s = 3.0
cool_timeout_s = 10.0
inner_heat_s = 0.5
inner_cool_s = 1.5
"""

def _plan(tmp_path: Path, text: str = PLAN) -> Path:
    p = tmp_path / "plan.toml"
    p.write_text(text.replace("{out}", str(tmp_path / "out")))
    return p


def test_example_plan_is_valid_and_its_dry_run_fits_in_minutes(cli):
    plan = load_plan(EXAMPLE)
    assert len(plan.steps) == 3 and plan.settings["mock_speed"] > 1
    proc = cli("plan", "run", EXAMPLE, "--dry-run", check=True)
    assert "load change" in proc.stdout and "limits:" in proc.stdout
    total = sum(planmod.step_budget(plan, s)["duration_s"] for s in plan.steps)
    assert total / plan.settings["mock_speed"] < 120  # a few minutes on the mock, at most


def test_dry_run_budget_numbers(tmp_path):
    from smabench.physics.wire import PRESETS

    plan = load_plan(_plan(tmp_path))
    r = PRESETS["paper"].resistance_ohm(0.0)
    a, b, c = (planmod.step_budget(plan, s) for s in plan.steps)
    assert a["duration_s"] == pytest.approx(2 * (2 + 8) + 4)
    assert a["energy_j"] == pytest.approx(1.0**2 * r * 2 * 2.0)
    assert b["peak_current_a"] == 1.5 and b["energy_j"] == pytest.approx(1.5**2 * r * 3.0)
    assert c["energy_j"] == pytest.approx(1.2**2 * r * (3.0 + 0.25 * 10.0))
    text = "\n".join(dry_run(plan))
    assert "peak current 1.50 A" in text and text.count("load change") == 1


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (("cycles = 2", "cycles = 0"), r"step 1: cycles must be in 1 … 10000, got 0 \(cycles\)"),
        # smabench run's range, not one of the plan's own (it let 10⁶ through to the session)
        (("cycles = 2", "cycles = 20000"), r"step 1: cycles must be in 1 … 10000"),
        (("heat_s = 2.0", "heat_s = 0.0"), r"heat time must be in \(0, 600\] s.*\(heat_s\)"),
        (("current_a = 1.5", "current_a = 1.5\ncurrant = 1"), "step 2: unknown key.*currant"),
        (('name = "b"', 'name = "a"'), "step names must be unique"),
        (('protocol = "inner"', 'protocol = "sine"'), "protocol 'sine' is not one of"),
        (("load_kg = 1.0", "load = 1.0"), "unknown key"),
        (("[plan]", "[plam]"), "unknown table"),
        (("cycles = 2", "cycles = 2.5"), "cycles must be int"),
        (("current_a = 1.5", "current_a = 2.4"), "step 2.*current"),
        (("heat_s = 2.0", "heat_s = [2"), "not valid TOML"),
    ],
)
def test_plan_validation_names_the_problem(tmp_path, capsys, edit, match):
    from smabench.cli import main

    text = PLAN.replace(*edit, 1)
    p = _plan(tmp_path, text)
    with pytest.raises(PlanError, match=match):
        load_plan(p)
    capsys.readouterr()
    assert main(["plan", "run", str(p), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("smabench plan: error:")


class FakeBench:
    """Steps recorded as small real sessions; can 'crash' (the process dies) inside a step."""

    def __init__(self, crash_in: str | None = None, abort: dict | None = None) -> None:
        self.crash_in = crash_in
        self.abort = dict(abort or {})  # step name -> reasons of its next runs' aborts
        self.ran: list[str] = []

    def __call__(self, plan, step, sid, dev):
        from smabench.bench.runtime import RunResult

        folder = plan.folder / sid
        w = SessionWriter(folder, {"load_kg": step["load_kg"]})
        w.append({"t_s": 0.0, "current_A": step["current_a"], "position_mm": 1.0, "cycle": 0})
        self.ran.append(sid)
        if step["name"] == self.crash_in:
            self.crash_in = None
            raise SystemExit("power lost")  # the session stays 'running', as after a crash
        reasons = self.abort.get(step["name"])
        if reasons:
            reason = reasons.pop(0)
            w.close("aborted", reason)
            cause = ("interlock" if reason.startswith("interlock") else
                     "safety" if reason.startswith("current driver fault") else "device")
            return folder, RunResult("aborted", reason, 1, cause=cause)
        w.close()
        return folder, RunResult("completed", "protocol completed", 1, cause="completed")


def test_load_change_prompt_stop_and_resume(tmp_path, monkeypatch):
    fake = FakeBench()
    monkeypatch.setattr(planmod, "_run_step_session", fake)
    plan = load_plan(_plan(tmp_path))
    asked: list[tuple] = []
    slept: list[float] = []

    def refuse(load, prev, step):
        asked.append((load, prev, step))
        return False

    state = new_state(plan)
    code = execute(plan, state, planmod.Devices(mock=True), ask=refuse, sleep=slept.append)
    assert code == 3 and asked == [(2.0, 1.0, "b")] and fake.ran == ["01-a"]
    assert slept == [pytest.approx(4.0 / 5)]  # the rest, at mock speed
    state, folder = load_state(plan.folder)
    assert [s["status"] for s in state["steps"]] == ["done", "pending", "pending"]
    code = execute(plan, state, planmod.Devices(mock=True), ask=lambda *a: True,
                   sleep=slept.append)  # fmt: skip
    assert code == 0 and fake.ran == ["01-a", "02-b", "03-c"]
    meta = json.loads((plan.folder / "03-c" / "session.json").read_text())
    assert meta["plan"]["step"] == "c" and meta["plan"]["previous_session"].endswith("02-b")
    assert json.loads((plan.folder / "01-a" / "session.json").read_text())["plan"]["index"] == 1


def test_crash_inside_a_step_resumes_there_with_the_sessions_linked(tmp_path, monkeypatch):
    fake = FakeBench(crash_in="b")
    monkeypatch.setattr(planmod, "_run_step_session", fake)
    plan = load_plan(_plan(tmp_path))
    with pytest.raises(SystemExit):
        execute(plan, new_state(plan), planmod.Devices(mock=True), ask=lambda *a: True,
                sleep=lambda s: None)  # fmt: skip
    state, _ = load_state(plan.folder / "plan-state.json")
    assert [s["status"] for s in state["steps"]] == ["done", "running", "pending"]
    assert load_session(plan.folder / "02-b").meta["status"] == "running"  # readable anyway
    code = execute(plan, state, planmod.Devices(mock=True), ask=lambda *a: True,
                   sleep=lambda s: None)  # fmt: skip
    assert code == 0 and fake.ran == ["01-a", "02-b", "02-b-r1", "03-c"]
    final, _ = load_state(plan.folder)
    b = final["steps"][1]
    assert b["status"] == "done" and b["session"].endswith("02-b-r1")
    assert b["interrupted"] == [str(plan.folder / "02-b")]
    meta = json.loads((plan.folder / "02-b-r1" / "session.json").read_text())
    assert meta["plan"]["interrupted_sessions"] == [str(plan.folder / "02-b")]


def test_resume_refuses_a_changed_plan_and_run_refuses_an_existing_state(tmp_path, monkeypatch,
                                                                         capsys):  # fmt: skip
    from smabench.cli import main

    monkeypatch.setattr(planmod, "_run_step_session", FakeBench())
    p = _plan(tmp_path)
    plan = load_plan(p)
    execute(plan, new_state(plan), planmod.Devices(mock=True), ask=lambda *a: False)
    capsys.readouterr()
    assert main(["plan", "run", str(p), "--mock"]) == 2
    assert "plan resume" in capsys.readouterr().err
    p.write_text(p.read_text().replace("cycles = 1", "cycles = 2"))
    assert main(["plan", "resume", str(plan.folder), "--mock"]) == 2
    assert "changed since the plan started" in capsys.readouterr().err


@pytest.mark.slow
def test_example_plan_on_the_mock_killed_and_resumed(tmp_path):
    """End to end on the mock bench: the example plan, SIGKILL during step 2 (a power loss),
    `plan resume` finishes it; every step's session is complete and linked."""
    text = EXAMPLE.read_text().replace('out = "sessions/plans-out"', f'out = "{tmp_path}"')
    # one cycle per step, a short rest and cooling: the kill, the resume and the links are what
    # is tested (the plan's full length is its dry run's, above), and each step still ends on
    # its own (its cooling ends by the protocol's settling or timeout, 4-5 s of device time)
    for long, short in (("cycles = 3", "cycles = 1"), ("cycles = 2", "cycles = 1"),
                        ("rest_s = 5.0", "rest_s = 1.0"), ("min_cool_s = 9.0", "min_cool_s = 4.0"),
                        ("min_cool_s = 8.0", "min_cool_s = 4.0"),
                        ("cool_timeout_s = 12.0", "cool_timeout_s = 5.0")):  # fmt: skip
        assert long in text
        text = text.replace(long, short)
    p = tmp_path / "example.toml"
    p.write_text(text)
    cmd = [sys.executable, "-m", "smabench.cli", "plan", "run", str(p), "--mock"]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    lines = []
    deadline = time.monotonic() + 240
    for line in proc.stdout:  # wait on the output, not on time
        lines.append(line)
        if ">>> step cycles-2kg" in line:
            proc.stdin.write("\n")
            proc.stdin.flush()
        if line.startswith("step 2/3"):
            break
        assert time.monotonic() < deadline, "".join(lines)
    state_file = tmp_path / "example" / "plan-state.json"
    deadline = time.monotonic() + 60
    while not (tmp_path / "example" / "02-cycles-2kg" / "samples.csv").exists():
        assert proc.poll() is None, "".join(lines)  # the plan ended (its stderr is above)
        assert time.monotonic() < deadline, "".join(lines)
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole process group: the plan and its mock
    proc.wait()
    state = json.loads(state_file.read_text())
    assert [s["status"] for s in state["steps"]] == ["done", "running", "pending"]
    res = subprocess.run([sys.executable, "-m", "smabench.cli", "plan", "resume",
                          str(tmp_path / "example"), "--mock"], input="", capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert "resuming at cycles-2kg" in res.stdout
    state = json.loads(state_file.read_text())
    assert [s["status"] for s in state["steps"]] == ["done", "done", "done"]
    # no step aborted by the (mock) devices and quietly run again: the plan's retries would hide
    # a bench that cannot hold its link on a busy machine
    assert [s.get("retried", 0) for s in state["steps"]] == [0, 0, 0], res.stdout + res.stderr
    for s in state["steps"]:
        sess = load_session(s["session"])
        assert sess.meta["status"] == "completed" and sess.meta["plan"]["step"] == s["name"]
    assert state["steps"][1]["interrupted"][0] == str(tmp_path / "example" / "02-cycles-2kg")
    shutil.rmtree(tmp_path / "example", ignore_errors=True)


def test_device_aborts_are_retried_unattended_interlocks_are_not(tmp_path, monkeypatch):
    fake = FakeBench(abort={"a": ["current driver telemetry lost for 0.25 s"],
                            "b": ["interlock: estimated temperature 170 °C above 160 °C"]})
    monkeypatch.setattr(planmod, "_run_step_session", fake)
    plan = load_plan(_plan(tmp_path))
    code = execute(plan, new_state(plan), planmod.Devices(mock=True), ask=lambda *a: True,
                   sleep=lambda s: None)  # fmt: skip
    assert code == 1 and fake.ran == ["01-a", "01-a-r1", "02-b"]
    state, _ = load_state(plan.folder)
    a, b = state["steps"][:2]
    assert a["status"] == "done" and a["session"].endswith("01-a-r1") and a["retried"] == 1
    assert json.loads((plan.folder / "01-a" / "session.json").read_text())["plan"]["superseded"]
    assert b["status"] == "tripped" and "interlock" in b["result"]


def test_a_safety_trip_ends_the_plan_and_resume_asks(tmp_path, monkeypatch, capsys):
    trip = "current driver fault: over-temperature (energy budget or thermocouple above the max)"
    fake = FakeBench(abort={"a": [trip, trip]})
    monkeypatch.setattr(planmod, "_run_step_session", fake)
    plan = load_plan(_plan(tmp_path))
    code = execute(plan, new_state(plan), planmod.Devices(mock=True), ask=lambda *a: True,
                   sleep=lambda s: None)  # fmt: skip
    assert code == 1 and fake.ran == ["01-a"]  # retries = 1 in the plan, yet not run again
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "over-temperature" in err[0] and "plan resume" in err[0]
    state, _ = load_state(plan.folder)
    assert state["steps"][0]["status"] == "tripped" and state["steps"][0]["cause"] == "safety"

    entry = state["steps"][0]
    import io

    monkeypatch.setattr(sys, "stdin", io.StringIO(""))  # nobody at the terminal: end of input
    with pytest.raises(PlanError, match="--yes"):
        planmod.confirm_after_trip(entry, yes=False)
    monkeypatch.setattr(sys, "stdin", io.StringIO("n\n"))
    assert not planmod.confirm_after_trip(entry, yes=False)
    monkeypatch.setattr(sys, "stdin", io.StringIO("yes\n"))
    assert planmod.confirm_after_trip(entry, yes=False)
    assert planmod.confirm_after_trip(entry, yes=True)


def test_predicted_peak_against_the_heat_balance(tmp_path):
    from smabench.physics.thermal import steady_state_temperature
    from smabench.physics.wire import PRESETS

    wire = PRESETS["paper"]
    plan = load_plan(_plan(tmp_path))
    long_heat = {**plan.steps[0], "heat_s": 600.0, "cycles": 1, "current_a": 1.0}
    hot = steady_state_temperature(1.0, wire, planmod.PEAK_AMBIENT_C,
                                   resistance_ohm=wire.resistance_ohm(0.0))  # fmt: skip
    assert planmod.predicted_peak_c(plan, long_heat) == pytest.approx(hot, abs=0.01)
    one = {**plan.steps[0], "cycles": 1}
    many = {**plan.steps[0], "cycles": 50, "min_cool_s": 0.5}  # short cooling ratchets up
    assert planmod.predicted_peak_c(plan, many) > planmod.predicted_peak_c(plan, one) + 5


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (("[plan]", "[plan]\ntemperature_limit_c = 60"), r"step 2 \(b\): predicted peak wire "
         r"temperature \d+ °C exceeds temperature_limit_c 60 °C"),
        (("[plan]", "[plan]\nmax_step_s = 15"), r"step 1 \(a\): takes up to 20 s, longer than "
         "max_step_s 15 s"),
    ],
)
def test_plan_refuses_a_step_over_the_limits(tmp_path, edit, match):
    with pytest.raises(PlanError, match=match):
        load_plan(_plan(tmp_path, PLAN.replace(*edit, 1)))


def test_a_plan_on_a_raw_port_follows_its_stable_name(tmp_path, monkeypatch):
    """`plan run --port /dev/ttyUSB0`: every step, and every retry of a step after a link loss,
    opens the adapter's stable name (udev's ``/dev/serial/by-id`` link), so a retry after a
    replug finds the adapter under its new device name, not a stranger under the old one."""
    import argparse

    master, slave = os.openpty()
    try:
        raw = os.ttyname(slave)
        by_id = tmp_path / "by-id"
        by_id.mkdir()
        stable = by_id / "usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0"
        stable.symlink_to(raw)
        monkeypatch.setenv("SMABENCH_SERIAL_BY_ID", str(by_id))
        args = argparse.Namespace(mock=False, port=raw, sensor="tcp:127.0.0.1:5020",
                                  sensor_map="generic-rs485-laser")  # fmt: skip
        assert planmod._devices(args).port == str(stable)
        stable.unlink()  # an adapter without a stable name: its device name as given
        assert planmod._devices(args).port == raw
    finally:
        os.close(master)
        os.close(slave)
