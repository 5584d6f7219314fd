"""The bench runtime and its control tick on simulated time, in-process.

Every session here is :class:`~smabench.bench.runtime.BenchRuntime` — the loop that runs on the
bench — scheduled on the simulated clock of :mod:`smabench.drivers.sim`, so the figures are the
same on a quiet and on a busy machine: the tick's fault handling (e-stop, stop, maximum duration,
lost sensor, flagged bursts, sensor status errors, lost telemetry, device faults, the
interlocks, a broken wire), its inputs (measured resistance, the driver's ambient, a command
every tick), the scheduler's missed deadlines, and the physics of recorded sessions (loops
shift up and narrow with load, incomplete cycles, inner loops, recorded positions that the plant
simulated offline reproduces). Device-side checks read the simulated plant.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from smabench.bench.offline import run_closed_loop
from smabench.bench.runtime import BenchRuntime
from smabench.bench.tick import ControlTick, RuntimeConfig
from smabench.commands import CommandStep
from smabench.drivers import protocol as p
from smabench.drivers.base import FLAG_SENSOR_STATUS, FLAG_TIMEOUT, Sample
from smabench.drivers.sim import SimBench
from smabench.physics.plant import simulate_plant
from smabench.protocols import Protocol, ProtocolSettings
from smabench.sessions import (
    FLAG_AFTER_END,
    FLAG_DEADLINE_MISSED,
    FLAG_FEEDBACK_RESISTANCE,
    FLAG_INTERLOCK,
    FLAG_SENSOR_INVALID,
    FLAG_TELEMETRY_STALE,
    EventLog,
    SessionWriter,
    load_session,
    read_events,
)

PERIOD_S = 0.005  # 200 Hz, the bench's default loop


class Constant:
    """A command source: ``current_a`` until ``duration_s``, then done; records what it saw."""

    def __init__(self, current_a: float, duration_s: float = math.inf) -> None:
        self.current_a, self.duration_s = current_a, duration_s
        self.positions: list[float] = []

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        self.positions.append(position_mm)
        done = t_s >= self.duration_s
        return CommandStep(0.0 if done else self.current_a, 0, "hold", done=done)


class Observing(Constant):
    """Also an observing source (a controller's seam): keeps what ``observe`` was given."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.observed: list[tuple] = []

    def observe(self, temperature_c, ambient_c, resistance_ohm, position_mm) -> None:
        self.observed.append((temperature_c, ambient_c, resistance_ohm, position_mm))


def session(command, bench: SimBench | None = None, at=None, **cfg):
    """Run one session on the simulated bench; ``at = {tick: fn(runtime, bench)}`` injects
    events before those ticks. Returns (result, rows, bench): the rows of the session itself;
    those recorded after its end (``after_end``, until the driver showed the output off) are
    ``bench.after_end_rows``."""
    bench = bench or SimBench(2.0, seed=1)
    rows: list[dict] = []
    cfg.setdefault("rate_hz", 1.0 / PERIOD_S)
    cfg.setdefault("max_duration_s", 30.0)
    rt_box: list[BenchRuntime] = []

    def on_tick(k: int, t_s: float) -> None:
        if at and k in at:
            at[k](rt_box[0], bench)

    rt = BenchRuntime(
        bench.source, bench.sensor, command, rows.append, RuntimeConfig(**cfg),
        on_tick=on_tick, clock=bench.clock.now, sleep=bench.clock.sleep,
    )  # fmt: skip
    rt_box.append(rt)
    result = rt.run()
    after = [(int(r["flags"]) & FLAG_AFTER_END) != 0 for r in rows]
    assert after == sorted(after), "after-end rows come only after the session's own"
    bench.after_end_rows = [r for r, a in zip(rows, after, strict=True) if a]
    assert result.samples == len(rows)
    return result, [r for r, a in zip(rows, after, strict=True) if not a], bench


def col(rows, name):
    return np.array([np.nan if r[name] is None else r[name] for r in rows], dtype=float)


def assert_output_off(bench: SimBench) -> None:
    """Device side: the driver is disabled and the wire gets no current."""
    bench.clock.sleep(0.01)
    assert not bench.source.enabled and bench.state.current_a == 0.0


# ----------------------------------------------------------------------------- seams
def test_the_tick_takes_typed_command_sources_only():
    with pytest.raises(TypeError, match="not a command source"):
        ControlTick(object())
    assert not ControlTick(Constant(0.5)).observing
    assert ControlTick(Observing(0.5)).observing


def test_the_current_is_commanded_every_tick():
    """The command renews the driver's setpoint lease, so it goes out on every tick even when
    it does not change."""
    result, rows, bench = session(Constant(0.5, duration_s=2.0 - PERIOD_S / 2))
    assert result.status == "completed" and result.samples == len(rows) == 401
    assert result.cause == "completed"
    # one ENABLE at the start, then one command per tick except the last (done: made safe)
    assert bench.source.commands == 1 + len(rows) - 1


def test_a_host_whose_loop_stops_commanding_loses_the_output():
    """Device side: once the setpoint is no longer renewed (a hung loop whose link thread still
    keeps the link alive), the lease expires and the output goes off; once nothing comes at
    all, the host timeout does the same."""
    bench = SimBench(2.0)
    src = bench.source
    src.enable(True)
    src.set_current(1.0)
    for _ in range(4):  # 0.2 s of keepalive-only traffic: inside the 0.25 s lease
        bench.clock.sleep(0.05)
        src.set_limits(2.5, 0.25)
    assert bench.state.current_a == pytest.approx(1.0, abs=0.01)
    bench.clock.sleep(0.06)
    src.set_limits(2.5, 0.25)  # the link is alive, the setpoint is not renewed
    assert src.current_a == 0.0 and src.setpoint_a == 0.0 and src.flags & p.Flag.LEASE_EXPIRED
    assert not src.flags & p.Flag.HOST_TIMEOUT
    src.enable(True)
    src.set_current(1.0)
    bench.clock.sleep(0.3)  # silence: host timeout and lease
    bench.plant.sync()  # the device side catches up with the clock
    assert src.current_a == 0.0 and src.flags & p.Flag.HOST_TIMEOUT
    assert bench.source.latest().flags & p.Flag.HOST_TIMEOUT


def test_the_estimate_uses_the_measured_resistance_and_the_drivers_ambient():
    bench = SimBench(2.0, ambient_c=30.0, seed=2)
    src = Observing(1.0, 3.0)
    result, rows, _ = session(src, bench)
    assert result.status == "completed"
    temps, ambients, resistances, positions = zip(*src.observed, strict=True)
    first = 2  # the first telemetry frame comes at 10 ms; before it, the configured 22 °C
    # the firmware's NTC reading (10-bit ADC, whole mV) resolves 0.02 K at 30 °C
    assert np.allclose(col(rows, "ambient_C")[first:], 30.0, atol=0.02)
    assert np.allclose(ambients[first:], 30.0, atol=0.02)
    assert temps[first] == pytest.approx(30.0, abs=0.1)  # the wire starts at the room's
    r = np.array([x for x in resistances if x is not None])
    # V/I of the telemetry, against the plant's resistance (mV and mA resolution)
    assert len(r) > 0.9 * len(resistances)
    assert np.allclose(r, bench.plant.plant.p.r_mean, rtol=0.01)
    assert all(x is not None and math.isfinite(x) for x in positions)


# ----------------------------------------------------------------------------- ending a session
@pytest.mark.parametrize(
    "event, status, reason, ticks",
    [
        (lambda rt, b: rt.estop(), "aborted", "e-stop", 0),
        (lambda rt, b: rt.stop(), "stopped", "stopped by operator", 0),
        # the fault reaches the host with the next telemetry frame (every 10 ms)
        (lambda rt, b: b.source.inject_fault(p.Flag.OVERCURRENT), "aborted",
         "current driver fault: overcurrent", 2),
    ],
    ids=["estop", "stop", "driver-fault"],
)  # fmt: skip
def test_operator_requests_and_device_faults_end_the_session_with_the_output_off(
    event, status, reason, ticks
):
    seen = {}

    def at_200(rt, b):
        event(rt, b)
        seen["current_a"] = b.source.current_a  # device side, right after the event

    result, rows, bench = session(Constant(1.2), at={200: at_200})
    assert result.status == status and result.reason.startswith(reason), result.reason
    # the driver's over-current trip is a safety trip (never retried by a plan), not a link loss
    assert result.cause == ("safety" if "fault" in reason else "operator")
    # the tick that sees the event records nothing and commands nothing
    assert 200 <= len(rows) <= 200 + ticks
    if status == "aborted":  # e-stop and fault: the output went off at once
        assert seen["current_a"] == 0.0
    assert_output_off(bench)


def test_the_maximum_duration_ends_the_session():
    result, rows, bench = session(Constant(0.5), max_duration_s=2.0)
    assert result.status == "aborted" and "maximum duration 2.0 s" in result.reason
    assert result.cause == "interlock"
    assert col(rows, "t_s")[-1] == pytest.approx(2.0, abs=PERIOD_S)
    assert_output_off(bench)


def test_a_lost_sensor_ends_the_session_after_its_timeout():
    result, rows, bench = session(Constant(0.8), at={100: lambda rt, b: b.sensor.fail()})
    t = col(rows, "t_s")
    assert result.status == "aborted" and "displacement sensor lost" in result.reason
    assert result.cause == "device"
    # the last valid reading was at tick 99; the timeout is 1 s
    assert t[-1] - t[99] == pytest.approx(1.0, abs=2 * PERIOD_S)
    flags = col(rows, "flags").astype(int)
    invalid = (flags & FLAG_SENSOR_INVALID) != 0
    assert np.all(invalid[100:]) and not np.any(invalid[:100])
    assert_output_off(bench)


@pytest.mark.parametrize("flag", [FLAG_TIMEOUT, FLAG_SENSOR_STATUS], ids=["timeout", "status"])
def test_a_burst_of_bad_samples_is_flagged_never_fed_to_the_controller_and_the_run_continues(
    flag,
):
    src = Observing(0.8, 2.0)
    result, rows, _ = session(src, at={100: lambda rt, b: b.sensor.fail(8, flag)})
    assert result.status == "completed"
    flags = col(rows, "flags").astype(int)
    bad = (flags & FLAG_SENSOR_INVALID) != 0
    assert np.flatnonzero(bad).tolist() == list(range(100, 108))
    assert np.all(flags[bad] & flag)  # the sensor's own bits are kept in the low byte
    pos = col(rows, "position_mm")
    assert np.all(np.isnan(pos[bad])) and np.all(np.isfinite(pos[~bad]))
    assert all(math.isnan(x) for x in src.positions[100:108])
    assert all(o[3] is None for o in src.observed[100:108])
    assert all(math.isfinite(x) for x in src.positions[108:])


def test_lost_telemetry_ends_the_session_within_the_link_timeout():
    result, rows, bench = session(Constant(0.8), at={100: lambda rt, b: b.source.stall_telemetry()})
    assert result.status == "aborted" and "telemetry lost for" in result.reason
    assert result.cause == "device"
    t = col(rows, "t_s")
    # frames every 10 ms, link timeout 0.25 s: the session ends within 0.27 s of the stall
    assert 0.24 <= t[-1] - t[100] <= 0.27
    assert_output_off(bench)


@pytest.mark.parametrize(
    "current_a, cfg, reason",
    [
        (2.2, {}, "interlock: commanded current 2.200 A outside 0 … 2.0 A"),
        (1.6, {"temperature_limit_c": 60.0}, "interlock: estimated temperature"),
        (1.6, {"position_min_mm": 2.0}, "interlock: position"),
    ],
    ids=["current", "temperature", "position"],
)
def test_interlocks_end_the_session_on_a_flagged_row_without_commanding(current_a, cfg, reason):
    result, rows, bench = session(Constant(current_a), **cfg)
    assert result.status == "aborted" and result.reason.startswith(reason), result.reason
    assert result.cause == "interlock"
    assert int(rows[-1]["flags"]) & FLAG_INTERLOCK
    assert not any(int(r["flags"]) & FLAG_INTERLOCK for r in rows[:-1])
    # the tripping command never reached the driver
    assert bench.source.setpoint_a <= 2.0 and rows[-1]["current_set_A"] == current_a
    assert_output_off(bench)
    if "temperature_limit_c" in cfg:
        assert rows[-1]["temperature_est_C"] > 60.0 >= rows[-2]["temperature_est_C"]


@pytest.mark.parametrize("current_a", [1.4, 0.0], ids=["heating", "cold"])
def test_a_broken_wire_ends_the_session_before_the_driver_notices(current_a):
    """The load falls: the position jumps further in one tick than the wire can move. The
    session ends within a few ticks, before the driver latches OPEN_WIRE (50 ms)."""
    result, rows, bench = session(Constant(current_a), at={300: lambda rt, b: b.plant.break_wire()})
    assert result.status == "aborted" and result.reason.startswith("broken wire: position jumped +")
    assert result.cause == "interlock"  # an unattended plan must not run the step again
    t = col(rows, "t_s")
    assert t[-1] - t[300] <= 0.035  # ≈ 1 mm per tick after 20 ms of free fall
    assert not bench.source.flags & p.Flag.OPEN_WIRE
    assert int(rows[-1]["flags"]) & FLAG_INTERLOCK
    assert_output_off(bench)


class Pulse(Constant):
    """``current_a`` for ``heat_s``, then 0 A until ``duration_s``."""

    def __init__(self, current_a: float, heat_s: float, duration_s: float) -> None:
        super().__init__(current_a, duration_s)
        self.heat_s = heat_s

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        step = super().update(t_s, position_mm)
        return step if t_s < self.heat_s else CommandStep(0.0, 0, "cool", done=step.done)


@pytest.mark.parametrize("rate_hz", [200.0, 20.0])
@pytest.mark.parametrize("load_kg", [1.0, 4.0])
def test_the_broken_wire_check_never_trips_on_the_wires_fastest_motion(rate_hz, load_kg):
    """Full contraction at the driver's 2.5 A hard limit, then cooling: the fastest motion the
    wire itself makes (≈ 23 mm/s) passes the check at 200 Hz and at 20 Hz."""
    bench = SimBench(load_kg, seed=4)
    src = Pulse(2.5, 1.2, 6.0)
    result, rows, _ = session(src, bench, rate_hz=rate_hz, current_limit_a=2.5)
    assert result.status == "completed", result.reason
    pos, t = col(rows, "position_mm"), col(rows, "t_s")
    assert np.ptp(pos) > 2.0  # it did contract fully
    assert np.max(np.abs(np.diff(pos) / np.diff(t))) > 10.0  # and fast, mm/s


# ----------------------------------------------------------------------------- scheduling
def test_a_late_tick_is_a_flagged_missed_deadline_and_the_schedule_restarts():
    bench = SimBench(2.0)
    stalls = {100: 0.02}  # the loop thread stalls 20 ms (4 periods) before tick 100

    def on_tick(k, t_s):
        if k in stalls:
            bench.clock.sleep(stalls.pop(k))

    rows: list[dict] = []
    rt = BenchRuntime(
        bench.source, bench.sensor, Constant(0.5, 1.0), rows.append,
        RuntimeConfig(rate_hz=200.0), on_tick=on_tick, clock=bench.clock.now,
        sleep=bench.clock.sleep,
    )  # fmt: skip
    result = rt.run()
    # the stall delays tick 100's work: tick 101 starts 15 ms late, no burst follows
    assert result.status == "completed" and result.missed_deadlines == 1
    flags = col(rows, "flags").astype(int)
    assert np.flatnonzero(flags & FLAG_DEADLINE_MISSED).tolist() == [101]
    t = col(rows, "t_s")
    assert t[101] - t[100] == pytest.approx(0.02, abs=1e-9)
    assert np.allclose(np.diff(t[101:]), PERIOD_S)  # the schedule restarts from the late tick
    assert result.periods_s.max() == pytest.approx(0.02, abs=1e-9)


def test_a_process_stopped_mid_tick_ends_as_its_stall_not_as_the_drivers_silence():
    """SIGSTOP can land anywhere in a tick: here in the sensor's read (or between the read and
    the tick), 2 s long. On resuming, the link's reader thread has not yet taken in the frames
    the kernel buffered, so the newest frame is 2 s old: the driver did not go silent, this
    process did. The session ends on the process's stall (cause "host"), whatever the point
    where it was stopped; the lease turned the output off meanwhile (tests/faults/test_signals
    stops a real run; this is the race it met, made certain)."""
    bench = SimBench(2.0, seed=1)
    sensor, source = bench.sensor, bench.source
    stop_at = {"tick": 200}
    real_read, real_latest = sensor.read_or_flag, source.latest

    def read_or_flag():
        if sensor.reads == stop_at["tick"]:
            before = real_latest()  # the newest frame this process had taken in
            bench.clock.sleep(2.0)  # stopped, the bench running on
            calls = {"n": 0}

            def latest_once():  # the reader thread runs only after the loop's next look
                calls["n"] += 1
                if calls["n"] <= 2:
                    return before
                source.latest = real_latest
                return real_latest()

            source.latest = latest_once
            return real_read()
        return real_read()

    sensor.read_or_flag = read_or_flag
    result, rows, _ = session(Constant(0.8), bench=bench)
    assert result.status == "aborted" and result.cause == "host", result.reason
    assert result.reason.startswith("the recording process stalled for 2.0"), result.reason
    assert_output_off(bench)


# ----------------------------------------------------------------------------- recorded physics
SPEED_PROTOCOLS = {
    "cycles": dict(cycles=2, heat_s=3.0, current_a=1.4),
    "incomplete": dict(cycles=3, heat_s=3.0, partial_cool_s=2.0, current_a=1.4),
    "inner": dict(cycles=5, heat_s=3.0, inner_heat_s=0.4, inner_cool_s=0.8, current_a=1.4),
}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Every protocol at 1 kg and 4 kg, recorded through the session writer and read back."""
    out = tmp_path_factory.mktemp("sessions")
    sessions = {}
    for name, kw in SPEED_PROTOCOLS.items():
        for load in (1.0, 4.0):
            folder = out / f"{name}-{load:g}kg"
            with SessionWriter(folder, {"load_kg": load}) as writer:
                tr = run_closed_loop(
                    Protocol(ProtocolSettings(name=name, **kw)), load, 120.0,
                    dt_s=PERIOD_S, seed=7, keep_rows=True,
                )  # fmt: skip
                assert tr.status == "completed" and tr.reason == "protocol completed"
                for row in tr.rows:
                    writer.append(row)
            sessions[(name, load)] = load_session(folder)
    return sessions


def _cold_hot(temp, pos):
    cold = np.median(pos[temp < np.percentile(temp, 5)])
    hot = np.median(pos[temp > np.percentile(temp, 95)])
    return float(cold), float(hot)


def _width_k(temp, pos):
    """Loop width: enclosed area / stroke, K."""
    area = abs(float(np.sum(0.5 * (pos[1:] + pos[:-1]) * np.diff(temp))))
    cold, hot = _cold_hot(temp, pos)
    return area / abs(cold - hot)


@pytest.mark.slow
def test_complete_cycles_shift_up_and_narrow_with_load(recorded):
    widths, colds = {}, {}
    for load in (1.0, 4.0):
        d = recorded[("cycles", load)].data
        assert d["cycle"].max() == 1
        assert np.nanmax(d["current_A"]) == pytest.approx(1.4, abs=0.005)
        last = d["cycle"] == 1
        cold, hot = _cold_hot(d["temperature_est_C"][last], d["position_mm"][last])
        assert cold - hot > 2.0  # the full stroke of the 55 mm wire, mm
        widths[load] = _width_k(d["temperature_est_C"][last], d["position_mm"][last])
        colds[load] = cold
    assert colds[4.0] > colds[1.0] + 0.2  # heavier: the loop moves up (a longer wire)
    assert widths[4.0] < widths[1.0] - 2.0  # … and gets narrower


@pytest.mark.slow
def test_recorded_positions_follow_the_plant(recorded):
    """The plant simulated offline on the recorded current reproduces the recorded positions:
    the recorded time, current and position belong together."""
    for load in (1.0, 4.0):
        d = recorded[("cycles", load)].data
        current = np.nan_to_num(d["current_A"])  # empty before the first telemetry frame
        trace = simulate_plant(d["t_s"], current, load_kg=load, noise_mm=0.0)
        err = trace.position_mm - d["position_mm"]
        rms_pct = 100 * np.sqrt(np.mean(err**2)) / np.ptp(d["position_mm"])
        assert rms_pct < 1.0, f"{load} kg: {rms_pct:.2f} % of stroke"  # 0.4 % measured


@pytest.mark.slow
def test_incomplete_cycles_reheat_before_the_wire_cooled(recorded):
    d = recorded[("incomplete", 1.0)].data
    cold, hot = _cold_hot(d["temperature_est_C"], d["position_mm"])
    for k in (0, 1):  # cycles 0 and 1 reheat after 2 s of cooling
        end = d["position_mm"][d["cycle"] == k][-1]
        assert end < cold - 0.1 * (cold - hot), (k, end)


@pytest.mark.slow
def test_inner_loops_stay_inside_the_major_loop(recorded):
    d = recorded[("inner", 4.0)].data
    inner = (d["cycle"] >= 1) & (d["cycle"] <= 3)
    assert np.ptp(d["position_mm"][inner]) < 0.8 * np.ptp(d["position_mm"])
    assert np.ptp(d["temperature_est_C"][inner]) < 0.8 * np.ptp(d["temperature_est_C"])


def test_sample_type_is_what_the_sim_sensor_returns():
    bench = SimBench(2.0)
    s = bench.sensor.read_or_flag()
    assert isinstance(s, Sample) and math.isfinite(s.position_mm) and s.flags == 0


# --------------------------------------------------------------------------- bench priority
def test_bench_priority_lowers_the_nice_value_and_leaves_the_sessions_autogroup(
    tmp_path, monkeypatch
):
    """The process nice is lowered; the session's autogroup nice is left alone (lowered, it
    lifts every process of the session above the kernel's tty workers that carry the link);
    refused (no CAP_SYS_NICE): False."""
    from smabench.bench import priority

    group = tmp_path / "autogroup"
    group.write_text("/autogroup-1 nice 0\n")
    monkeypatch.setattr(priority, "AUTOGROUP", str(group))
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(priority.os, "setpriority", lambda *a: calls.append(a))
    assert priority.raise_priority(-7) is True
    assert calls == [(priority.os.PRIO_PROCESS, 0, -7)]
    assert group.read_text() == "/autogroup-1 nice 0\n"

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "setpriority", refuse)
    assert priority.raise_priority() is False


def fake_scheduler(monkeypatch, policy: int, prio: int) -> dict:
    """The calling thread's scheduling as a dict the priority helpers read and set."""
    from smabench.bench import priority

    state = {"policy": policy, "prio": prio}
    monkeypatch.setattr(priority.os, "sched_getscheduler", lambda pid: state["policy"])
    monkeypatch.setattr(priority.os, "sched_getparam",
                        lambda pid: priority.os.sched_param(state["prio"]))  # fmt: skip

    def setsched(pid, policy, param):
        state["policy"], state["prio"] = policy, param.sched_priority

    monkeypatch.setattr(priority.os, "sched_setscheduler", setsched)
    return state


def test_realtime_thread_puts_the_scheduling_back(monkeypatch):
    """``bench control`` runs each live session's loop real-time and then computes the next
    case at the scheduling it had: raised inside the block, put back after (also on error);
    where the system refuses, nothing changes and the block still runs."""
    from smabench.bench import priority

    state = fake_scheduler(monkeypatch, priority.os.SCHED_OTHER, 0)
    with pytest.raises(RuntimeError), priority.realtime_thread() as raised:
        assert raised is True
        assert state == {"policy": priority.os.SCHED_FIFO, "prio": priority.LOOP_RT_PRIORITY}
        raise RuntimeError("session failed")
    assert state == {"policy": priority.os.SCHED_OTHER, "prio": 0}

    def refuse(*a):
        raise PermissionError("no CAP_SYS_NICE")

    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    with priority.realtime_thread() as raised:
        assert raised is False
    assert state == {"policy": priority.os.SCHED_OTHER, "prio": 0}


# ----------------------------------------------------------------------------- the record proves it
def events_session(tmp_path, command, at, **cfg):
    """:func:`session` with an event log in ``tmp_path``; returns (result, rows, bench, events)."""
    log = EventLog(tmp_path)
    bench = SimBench(2.0, seed=1)
    rows: list[dict] = []
    box: list[BenchRuntime] = []
    cfg.setdefault("max_duration_s", 30.0)
    rt = BenchRuntime(
        bench.source, bench.sensor, command, rows.append, RuntimeConfig(**cfg),
        on_tick=lambda k, t: at[k](box[0], bench) if k in at else None,
        clock=bench.clock.now, sleep=bench.clock.sleep, events=log,
    )  # fmt: skip
    box.append(rt)
    result = rt.run()
    return result, rows, bench, read_events(tmp_path)


def test_an_estopped_session_records_until_the_current_is_off_and_logs_the_chain(tmp_path):
    result, rows, bench, events = events_session(
        tmp_path, Constant(1.4), {300: lambda rt, b: rt.estop(b.clock.now() - 0.004, "key Esc")}
    )
    assert result.status == "aborted" and result.reason == "e-stop"
    after = [r for r in rows if int(r["flags"]) & FLAG_AFTER_END]
    assert 1 <= len(after) <= 20, len(after)  # frames every 10 ms: off within a few
    assert abs(after[-1]["current_A"]) < 0.02 and after[-1]["current_set_A"] == 0.0
    live = [r for r in rows if not int(r["flags"]) & FLAG_AFTER_END]
    assert live[-1]["current_A"] == pytest.approx(1.4, abs=0.05)  # the e-stop came mid-heating
    assert [e["event"] for e in events] == [
        "estop_input", "command_sent", "session_end", "command_sent", "output_off_frame",
        "current_below_threshold",
    ]  # fmt: skip
    first = events[0]
    assert first["source"] == "key Esc"
    times = [e["t_host_s"] for e in events]  # one clock: the runtime's (simulated here)
    assert times == sorted(times) and times[-1] - times[0] < 0.1, times
    assert first["from_input_event"] is True
    assert events[1]["command"] == "ENABLE 0" and events[1]["why"] == "e-stop"
    assert events[2]["reason"] == "e-stop"
    assert events[-1]["current_a"] < 0.02 and events[-1]["threshold_a"] == 0.02
    assert events[-1]["t_device_ms"] >= events[-2]["t_device_ms"]


def test_a_lost_driver_is_recorded_as_not_confirmed_with_the_reason(tmp_path):
    result, rows, bench, events = events_session(
        tmp_path, Constant(0.8), {100: lambda rt, b: b.source.stall_telemetry()}
    )
    assert result.status == "aborted" and "telemetry lost" in result.reason
    names = [e["event"] for e in events]
    assert names[-1] == "output_off_not_confirmed", names
    assert "device is lost" in events[-1]["reason"]
    assert events[-1]["waited_s"] < 0.02  # already lost at the end: said at once, no wait
    after = [r for r in rows if int(r["flags"]) & FLAG_AFTER_END]
    assert 1 <= len(after) <= 4


def test_a_completed_session_ends_without_after_end_rows(tmp_path):
    result, rows, bench, events = events_session(tmp_path, Constant(0.5, duration_s=1.0), {})
    assert result.status == "completed"
    assert not [r for r in rows if int(r["flags"]) & FLAG_AFTER_END]
    assert [e["event"] for e in events] == ["session_end", "command_sent"]


class _DiesAfterOff:
    """A driver that, from ``off_at`` s of simulated time, sends a frame with its output off and
    no fault (its own shutdown), then goes silent: what a mock process killed under a run does."""

    def __init__(self, source, clock, off_at_s: float) -> None:
        self._src, self._clock, self.off_at_s = source, clock, off_at_s
        self._last = None

    def __getattr__(self, name):
        return getattr(self._src, name)

    def latest(self):
        now = self._clock.now()
        if now < self.off_at_s:
            self._last = self._src.latest()
        elif now < self.off_at_s + 0.01 and self._last is not None:
            self._last = dataclasses.replace(self._last, flags=p.Flag(0), host_time=now)
        return self._last

    def telemetry_age_s(self):
        return None if self._last is None else self._clock.now() - self._last.host_time


def test_a_driver_that_goes_off_with_no_reason_then_silent_is_named_lost(tmp_path):
    bench = SimBench(2.0, seed=1)
    source = _DiesAfterOff(bench.source, bench.clock, off_at_s=1.0)
    rows: list[dict] = []
    rt = BenchRuntime(
        source, bench.sensor, Constant(1.0), rows.append, RuntimeConfig(max_duration_s=30.0),
        clock=bench.clock.now, sleep=bench.clock.sleep, events=EventLog(tmp_path),
    )  # fmt: skip
    result = rt.run()
    assert result.status == "aborted" and result.reason.startswith("current driver lost"), result
    events = read_events(tmp_path)
    assert [e["event"] for e in events][-2:] == ["output_off_not_confirmed", "session_end_reason"]
    live = [r for r in rows if not int(r["flags"]) & FLAG_AFTER_END]
    assert live[-1]["t_s"] < 1.0 + 0.02  # nothing after the loss looks live


def test_rows_after_the_drivers_last_frame_are_flagged_stale_until_the_loss():
    result, rows, bench = session(Constant(0.8), at={100: lambda rt, b: b.source.stall_telemetry()})
    flags = col(rows, "flags").astype(int)
    stale = (flags & FLAG_TELEMETRY_STALE) != 0
    t = col(rows, "t_s")
    assert not stale[60:100].any()  # frames every 10 ms: live
    late = t > t[100] + 0.06  # the last frame came at most 10 ms before the stall
    assert stale[late].all() and late.sum() >= 30  # none of the rows before the loss looks live


def test_normal_thread_lowers_a_real_time_thread_for_a_computation(monkeypatch):
    """The GUI's runtime builds a controller's model on a real-time thread: lowered to normal
    scheduling for it, put back after (also on error); a normal thread is left alone."""
    from smabench.bench import priority

    state = fake_scheduler(monkeypatch, priority.os.SCHED_FIFO, 10)
    with pytest.raises(RuntimeError), priority.normal_thread() as lowered:
        assert lowered is True
        assert state == {"policy": priority.os.SCHED_OTHER, "prio": 0}
        raise RuntimeError("model failed")
    assert state == {"policy": priority.os.SCHED_FIFO, "prio": 10}
    state.update(policy=priority.os.SCHED_OTHER, prio=0)
    with priority.normal_thread() as lowered:
        assert lowered is False
    assert state == {"policy": priority.os.SCHED_OTHER, "prio": 0}


# ----------------------------------------------------------------------------- a silent sensor
@pytest.mark.slow
def test_a_silent_sensor_does_not_hold_up_the_loop_that_runs_on_the_estimate():
    """The laser stops answering for 10 s while PID holds mid-stroke with the resistance
    fallback: every request to it waits its Modbus timeout (50 ms, ten loop periods), so while
    it is silent the loop asks it in the background every SENSOR_PROBE_WHILE_SILENT_S and keeps
    its rate on the estimate; it reads every tick again once the sensor answers. (On the mock bench
    over TCP the loop asked every tick: 20 Hz instead of 80, the hold drifted 45 % of the
    stroke and the driver's host timeout ended the session.)"""
    from smabench import selfsense_bench as sb
    from smabench.bench.runtime import SENSOR_PROBE_WHILE_SILENT_S
    from smabench.control import ControllerSettings, build_controller
    from smabench.physics.wire import PAPER_WIRE

    cal = sb.closed_loop_calibration(1.0)
    bench = sb._bench(1.0, 31)
    bench.sensor.timeout_s = 0.05
    proto = ProtocolSettings(name="step", cycles=1, period_s=100.0, amplitude_mm=0.4,
                             lead_in_s=0.0)  # fmt: skip
    controller = build_controller(proto, ControllerSettings(mode="pid"), sb.LOAD_KG, PAPER_WIRE,
                                  2.0)  # fmt: skip
    asked_at: list[float] = []
    real_read, real_background = bench.sensor.read_or_flag, bench.sensor.read_in_background

    def read_or_flag():
        asked_at.append(bench.clock.now())
        return real_read()

    def read_in_background():
        asked_at.append(bench.clock.now())
        return real_background()

    bench.sensor.read_or_flag = read_or_flag
    bench.sensor.read_in_background = read_in_background
    t_drop = {}

    def drop(rt, b):
        t_drop["t"] = b.clock.now()
        b.sensor.fail_for(10.0)

    k0 = int(round(15.0 / PERIOD_S))
    result, rows, _ = session(controller, bench=bench, at={k0: drop}, max_duration_s=30.0,
                              selfsense=cal, fallback="resistance", probe_current_a=sb.PROBE_A,
                              wire=PAPER_WIRE)  # fmt: skip
    assert "maximum duration" in result.reason, result.reason
    t, flags = col(rows, "t_s"), col(rows, "flags").astype(int)
    on_est = (flags & FLAG_FEEDBACK_RESISTANCE) != 0
    gone = (t >= 15.0) & (t < 25.0)
    periods = np.diff(t[gone])
    asked = int(np.sum((np.array(asked_at) >= t_drop["t"])
                       & (np.array(asked_at) < t_drop["t"] + 10.0)))  # fmt: skip
    print(f"\nsilent 10 s: {int(gone.sum())} ticks, {asked} requests to the sensor, longest "
          f"period {periods.max() * 1e3:.1f} ms, {int(on_est.sum())} rows on the estimate")
    assert on_est[gone].mean() > 0.98 and not on_est[t >= 25.5].any()
    # its rate: held once, by the request in line that found the sensor silent
    assert gone.sum() >= 0.99 * 10.0 / PERIOD_S and np.sum(periods > 1.5 * PERIOD_S) <= 1
    assert asked <= 10.0 / SENSOR_PROBE_WHILE_SILENT_S * 1.1 + 2
    sp, pos = col(rows, "setpoint_mm"), col(rows, "position_mm")
    back = t >= 26.0
    assert np.nanmax(np.abs(pos[back] - sp[back])) < 0.1  # on the laser again, holding
