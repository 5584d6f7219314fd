"""Controllers: PID anti-windup, FF inverse round trip, kinetic lags, the temperature observer,
tracking targets in the offline loop, bumpless switching, refused setpoints, per-load gains, the
runtime's mode interface, and a smoke run of ``smabench bench control`` on the mock."""

from __future__ import annotations

import math
import os
import signal
import threading

import numpy as np
import pytest

from smabench.bench.offline import run_closed_loop
from smabench.bench.runtime import BenchRuntime
from smabench.control import ControllerSettings, PIDGains, build_controller, parse_switch
from smabench.control.controller import MODES
from smabench.control.factory import kinetic_lag_for, loop_model_for
from smabench.control.model import InverseLoop
from smabench.control.pid import PID, gains_for_load
from smabench.physics.effects import Effects
from smabench.physics.wire import PAPER_WIRE
from smabench.protocols import ProtocolSettings

LATENT = Effects(latent_heat=24000)


def make(mode="ffpid", kind="sine", period=20.0, load=2.0, **kw):
    p = ProtocolSettings(name=kind, cycles=2, period_s=period, amplitude_mm=kw.pop("amp", 0.8))
    return build_controller(p, ControllerSettings(mode=mode, **kw), load, PAPER_WIRE, 2.0)


# --------------------------------------------------------------------------- PID
def test_integrator_does_not_wind_up_while_saturated_or_cooling_passively():
    pid = PID(PIDGains(0.3, 0.2, 0.0))
    # wire far too long for 100 s with the output at its maximum: the integral stays bounded
    for _ in range(10_000):
        out = pid.update(0.01, setpoint=0.5, measurement=2.5, out_min_w=0.0, out_max_w=1.0)
    assert out == 1.0 and pid.integral_w <= 1.0 + 1e-12
    # the error changes sign: the output leaves the limit at once (no wound-up integral)
    out = pid.update(0.01, setpoint=2.5, measurement=2.4, out_min_w=0.0, out_max_w=1.0)
    assert out < 1.0
    # passive cooling: wire too short, output pinned at 0 for 100 s
    pid = PID(PIDGains(0.3, 0.2, 0.0))
    for _ in range(10_000):
        out = pid.update(0.01, setpoint=2.0, measurement=0.5, out_min_w=0.0, out_max_w=1.0)
    assert out == 0.0 and pid.integral_w >= -1e-12
    out = pid.update(0.01, setpoint=0.5, measurement=0.6, out_min_w=0.0, out_max_w=1.0)
    assert out > 0.0  # heats on the first tick the wire is too long again


def test_integrator_windup_in_closed_loop_with_an_unreachable_hold():
    """A long hold the wire cannot follow (current limit 0.6 A), then a reachable setpoint:
    with anti-windup the PID reaches it without the overshoot a wound-up integral gives."""
    c = make("pid", kind="step", period=60.0)
    c.current_limit_a = 0.6  # far too little to reach the hot setpoint
    tr = run_closed_loop(c, 2.0, 38.0, dt_s=0.02)
    hot = (tr.t_s > 8.0) & (tr.t_s < 38.0)
    assert np.all(tr.current_a[hot] <= 0.6 + 1e-9)
    assert abs(c.pid.integral_w) <= 0.6**2 * PAPER_WIRE.resistance_mean_ohm + 1e-9


def test_ffpid_integrator_does_not_wind_up_while_the_current_is_saturated():
    """FF+PID's PID (its output shifts the setpoint in mm) under the same unreachable hold:
    it stops integrating while the command sits at its maximum, and once the reachable
    setpoint comes it is near the others' error within a few seconds."""
    c = make("ffpid", kind="step", period=60.0)
    c.current_limit_a = 0.6
    shifts = []
    tr = run_closed_loop(c, 2.0, 38.0, on_tick=lambda k, t: shifts.append(c.ffpid.integral_w))
    hot = (tr.t_s > 9.0) & (tr.t_s < 38.0)
    assert np.all(tr.current_a[hot] <= 0.6 + 1e-9)
    assert np.max(np.abs(np.asarray(shifts)[: tr.t_s.size][hot])) < 0.1  # mm, limit is 1 mm


def test_derivative_acts_on_the_measurement_not_on_setpoint_steps():
    pid = PID(PIDGains(0.0, 0.0, 1.0, 0.1))
    pid.update(0.01, 1.0, 1.0, 0.0, 10.0)
    out = pid.update(0.01, 0.0, 1.0, 0.0, 10.0)  # setpoint step, measurement still
    assert out == 0.0


# --------------------------------------------------------------------------- feed-forward
@pytest.mark.parametrize("load", [1.0, 4.0])
def test_ff_inverse_round_trips_with_the_forward_model(load):
    fit = loop_model_for(load, PAPER_WIRE, "sigmoid")
    inv = InverseLoop(fit.loop_model, 22.0, 120.0, adapt=False)
    lo, hi = inv.reachable_mm()
    for heating in (True, False):
        for y in np.linspace(lo, hi, 15):
            fresh = InverseLoop(fit.loop_model, 22.0, 120.0, adapt=False, heating=heating)
            t = fresh.temperature(y)
            assert fresh.forward(t, heating) == pytest.approx(y, abs=0.01 * (hi - lo))
    # and temperature → position → temperature inside the steep part of each branch
    for heating, temps in ((True, (68.0, 70.0, 72.0)), (False, (46.0, 48.0, 50.0))):
        for t in temps:
            y = inv.forward(t, heating)
            fresh = InverseLoop(fit.loop_model, 22.0, 120.0, adapt=False, heating=heating)
            assert fresh.temperature(y) == pytest.approx(t, abs=0.3)


def test_ff_power_inverts_the_heat_balance_and_never_goes_negative():
    c = make("ff")
    ff = c.ff
    ff.sync(60.0)
    t_next = 61.0
    p = ff.power(t_next, 5.0)
    ff.advance(ff.horizon_s, p)  # held over the horizon, the power lands on the target
    assert ff.t_ff_c == pytest.approx(t_next, abs=1e-9)
    ff.sync(60.0)
    p_sink = ff.power(t_next, 5.0, disturbance_w=-0.1)  # a heat sink needs that much more
    assert p_sink == pytest.approx(p + 0.1, abs=1e-12)
    ff.sync(90.0)
    assert ff.power(40.0, 5.0) == 0.0  # faster than natural cooling: passive, not < 0


def _rms_after_lead_in(c, load, effects=None):
    tr = run_closed_loop(c, load, c.reference.duration_s, effects=effects)
    m = tr.t_s >= c.reference.s.lead_in_s
    return float(np.sqrt(np.mean((tr.position_mm[m] - tr.setpoint_mm[m]) ** 2)))


@pytest.mark.slow
@pytest.mark.parametrize("effects", [None, LATENT], ids=["nominal", "latent-heat"])
def test_ffpid_halves_the_pid_error_on_a_slow_sine_in_the_offline_loop(effects):
    """The issue's target on the 20 s sine, also with latent heat in the plant (which the
    controllers' model does not know); both laws with their per-load gains."""
    rms = {mode: _rms_after_lead_in(make(mode), 2.0, effects) for mode in ("pid", "ffpid")}
    assert rms["ffpid"] <= 0.5 * rms["pid"], rms


def test_kinetic_lag_is_identified_per_branch():
    heating_s, cooling_s = kinetic_lag_for(2.0, PAPER_WIRE, "sigmoid")
    # the plant's martensite fraction lags with 0.05 s (heating) and 0.5 s (cooling)
    assert 0.02 <= heating_s <= 0.08 and 0.3 <= cooling_s <= 0.6


@pytest.mark.slow
def test_observer_follows_the_wire_temperature_that_latent_heat_moves():
    """With latent heat in the plant the heat balance alone is off by several kelvin; the
    observer, fed the position through the loop model, follows the real temperature."""
    c = make("ffpid")
    seen = []
    tr = run_closed_loop(c, 2.0, 40.0, effects=LATENT,
                         on_tick=lambda k, t: seen.append(c.observer.temperature_c))  # fmt: skip
    m = tr.t_s > 10.0
    obs = np.asarray(seen[: tr.t_s.size])[m]
    err_obs = np.sqrt(np.mean((obs - tr.temperature_c[m]) ** 2))
    err_heat_balance = np.sqrt(np.mean((tr.estimate_c[m] - tr.temperature_c[m]) ** 2))
    assert err_heat_balance > 3.0, err_heat_balance
    assert err_obs < 0.25 * err_heat_balance, (err_obs, err_heat_balance)


def test_observer_estimates_no_heat_input_on_the_nominal_plant():
    c = make("ffpid")
    heat = []
    run_closed_loop(c, 2.0, 40.0, on_tick=lambda k, t: heat.append(c.observer.disturbance_w))
    assert np.mean(np.abs(heat[800:])) < 0.02  # W; the latent-heat sink peaks near 0.1 W


@pytest.mark.slow
def test_observer_gate_stays_shut_on_the_nominal_plant_and_opens_with_latent_heat():
    """The observer corrects only when the open-loop model (loop model at the heat balance's
    temperature) is measurably wrong: not on the plant the model was identified on."""
    for effects, lo, hi in ((None, 0.0, 0.05), (LATENT, 0.9, 1.0)):
        c = make("ffpid")
        gate = []
        run_closed_loop(c, 2.0, 40.0, effects=effects,
                        on_tick=lambda k, t, c=c, g=gate: g.append(c.observer.gate))  # fmt: skip
        mean = float(np.mean(gate[800:]))  # after the lead-in
        assert lo <= mean <= hi, (effects, mean)


def test_observer_gate_stays_shut_on_a_nominal_4_kg_staircase():
    """Minor branches after the staircase's reversals: the open-loop model starts them at the
    wire's measured position (as the inverse does), so it does not drift from the wire and
    open the gate on the plant the model was identified on (the model's own reversal points
    drifted 1 mm within four stairs at a 17.5 ms loop period)."""
    p = ProtocolSettings(name="staircase", cycles=1, period_s=40.0, amplitude_mm=0.8)
    c = build_controller(p, ControllerSettings(mode="ffpid"), 4.0, PAPER_WIRE, 2.0)
    gate = []
    run_closed_loop(c, 4.0, 48.0, dt_s=0.0175, seed=5,
                    on_tick=lambda k, t: gate.append(c.observer.gate))  # fmt: skip
    assert max(gate) < 0.5 and np.mean(gate) < 0.05, (max(gate), np.mean(gate))


def test_ffpid_uses_hold_gains_on_holds_and_tracking_gains_while_the_setpoint_moves():
    hold, track = gains_for_load(2.0, law="ffpid_hold"), gains_for_load(2.0, law="ffpid")
    assert hold.kp == 0.0 and 0.0 < hold.ki < track.ki
    c = make("ffpid")  # sine after an 8 s lead-in hold
    used, shifts = [], []

    def tick(k, t):
        used.append(c.ffpid.gains)
        shifts.append(c.ffpid.last_output_w)

    tr = run_closed_loop(c, 2.0, 12.0, on_tick=tick)
    t = tr.t_s
    assert all(g == hold for g, tt in zip(used, t, strict=True) if 1.0 < tt < 7.9)
    assert all(g == track for g, tt in zip(used, t, strict=True) if 8.5 < tt < 12.0)
    # the switch moves the proportional term into the integral: no step in the shift (mm)
    k = next(i for i, g in enumerate(used) if g == track)
    assert abs(shifts[k + 1] - shifts[k]) < 0.01
    assert c.describe()["ffpid_hold_gains"] == hold.as_dict()


def test_live_gain_changes_for_both_ffpid_sets_in_one_tick_are_both_applied():
    c = make("ffpid", period=20.0)

    def tick(k, t):
        if k == 800:  # 10 s: the sine is moving
            c.set_gains(0.25, 1.0, 0.0, law="ffpid")
            c.set_gains(0.0, 0.03, 0.0, law="ffpid_hold")

    run_closed_loop(c, 2.0, 12.0, on_tick=tick)
    assert (c.ffpid.gains.kp, c.ffpid.gains.ki) == (0.25, 1.0)  # moving: in use
    assert c.describe()["ffpid_hold_gains"]["ki"] == 0.03
    with pytest.raises(ValueError, match="pid, ffpid or ffpid_hold"):
        c.set_gains(0.1, 0.1, 0.0, law="ff")


@pytest.mark.slow
@pytest.mark.parametrize("load, ratio", [(1.0, 0.9), (2.0, 0.9), (4.0, 1.0)])
def test_ffpid_is_no_worse_than_pid_on_steps_in_the_offline_loop(load, ratio):
    """The issue's step target (≤ 1): the feed-forward lands the step, the hold gains only trim.
    Measured with the reference driver's current (the linear sink, ≈ 2 ms): 0.86 at 1 kg and
    0.87 at 2 kg; the gains were tuned when the offline loop had an 8 ms first-order current
    lag, which gave 0.69 and 0.71 (with the tracking gains on the holds: 0.84–0.92)."""
    rms = {m: _rms_after_lead_in(make(m, kind="step", period=30.0, load=load), load, None)
           for m in ("pid", "ffpid")}  # fmt: skip
    assert rms["ffpid"] <= ratio * rms["pid"], rms


def test_amplitude_refit_outside_its_range_is_not_used():
    """Samples the kinetic lag displaced (right after a step) can ask for an amplitude far
    outside the plausible range: the inverse then keeps the amplitude it had."""
    fit = loop_model_for(2.0, PAPER_WIRE, "sigmoid")
    for factor, accepted in ((3.0, False), (1.3, True)):
        inv = InverseLoop(fit.loop_model, 22.0, 120.0)
        inv.temperature(2.0)  # heating branch, major
        start, target = inv._start_target()
        for t in np.linspace(max(inv.low[0], 30.0), 90.0, 40):  # the wire deeper than the model
            chord = start[1] + (t - start[0]) / (target[0] - start[0]) * (target[1] - start[1])
            y = chord + factor * (inv.forward(t, True) - chord)
            inv.observe(float(t), float(y))
        if accepted:
            assert inv.refits == [pytest.approx(factor, rel=0.05)]
        else:
            assert inv.refits == [] and inv.scale[True] == 1.0


@pytest.mark.slow
def test_adaptation_moves_the_first_common_point_to_the_wire_reversal():
    c = make("ffpid")
    run_closed_loop(c, 2.0, 60.0, dt_s=0.02)
    inv = c.ff.inverse
    assert inv.reversals >= 3 and inv.refits
    # the reversal points come from the wire (estimated T, measured position)
    assert all(inv.low[0] < t < inv.high[0] for t, _ in inv.stack)


# --------------------------------------------------------------------------- switching
def test_switching_modes_mid_run_leaves_no_current_jump():
    c = make("pid")
    plan = {700: "ff", 1000: "ffpid", 1400: "open_loop", 1450: "pid", 2000: "ffpid"}
    switch_ticks = []

    def on_tick(k, t):
        if k in plan:
            c.set_mode(plan[k])
            switch_ticks.append(k)

    tr = run_closed_loop(c, 2.0, 70.0, dt_s=0.02, on_tick=on_tick)
    i = tr.current_a
    assert [tr.mode[k] for k in switch_ticks] == list(plan.values())
    steps = np.abs(np.diff(i))
    typical = np.percentile(steps, 95)
    for k in switch_ticks:
        # the commanded current at the switching tick equals the previous command
        assert abs(i[k] - i[k - 1]) <= max(0.02, typical), (k, tr.mode[k], i[k - 1], i[k])


def test_scripted_switches_and_mode_validation():
    assert parse_switch("30:ff") == (30.0, "ff")
    with pytest.raises(ValueError, match="unknown mode"):
        parse_switch("30:bang")
    with pytest.raises(ValueError, match="S:MODE"):
        parse_switch("soon:pid")
    c = make("pid", switches=[(10.0, "ff"), (20.0, "ffpid")])
    tr = run_closed_loop(c, 2.0, 30.0, dt_s=0.05)
    assert tr.mode[int(5 / 0.05)] == "pid"
    assert tr.mode[int(15 / 0.05)] == "ff" and tr.mode[int(25 / 0.05)] == "ffpid"
    with pytest.raises(ValueError, match="unknown mode"):
        c.set_mode("bang")


def test_setpoints_outside_the_reachable_stroke_are_refused():
    with pytest.raises(ValueError, match="outside the reachable stroke"):
        make("pid", amp=5.0)
    p = ProtocolSettings(name="sine", amplitude_mm=0.2, offset_mm=4.0)
    with pytest.raises(ValueError, match=r"setpoints 3\.800 … 4\.200 mm are outside"):
        build_controller(p, ControllerSettings(), 2.0, PAPER_WIRE, 2.0)


def test_reference_protocols_need_a_controller():
    with pytest.raises(ValueError, match="needs a controller"):
        ProtocolSettings(name="sine").validate(2.0)
    with pytest.raises(ValueError, match="open loop"):
        ProtocolSettings(name="cycles").validate(2.0, closed_loop=True)


# --------------------------------------------------------------------------- runtime interface
class _Dummy:
    def make_safe(self):
        pass


def test_runtime_mode_interface_is_validated_and_thread_safe():
    c = make("pid")
    rt = BenchRuntime(_Dummy(), _Dummy(), c, lambda row: None)
    assert rt.mode == "pid"
    threads = [threading.Thread(target=rt.set_mode, args=(m,)) for m in ("ff", "ffpid")]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert rt.mode in ("ff", "ffpid")
    rt.set_gains(0.2, 0.05, 0.0)
    with pytest.raises(ValueError, match="unknown mode"):
        rt.set_mode("turbo")
    with pytest.raises(ValueError):
        rt.set_gains(-1.0, 0.0, 0.0)
    # an open-loop protocol: only open_loop is accepted
    from smabench.protocols import Protocol

    rt2 = BenchRuntime(_Dummy(), _Dummy(), Protocol(ProtocolSettings()), lambda row: None)
    assert rt2.mode == "open_loop"
    with pytest.raises(ValueError, match="needs a controller"):
        rt2.set_mode("pid")
    with pytest.raises(ValueError, match="no PID"):
        rt2.set_gains(0.1, 0.1, 0.0)
    # a controller without a reference refuses closed-loop modes
    from smabench.control import Controller

    bare = Controller(PAPER_WIRE, 2.0, mode="open_loop")
    with pytest.raises(ValueError, match="reference"):
        bare.set_mode("pid")


def test_gains_are_stored_with_the_session_description():
    c = make("ffpid")
    d = c.describe()
    assert d["gains"]["kp"] > 0 and d["load_kg"] == 2.0
    assert d["reference"]["kind"] == "sine" and "reachable_mm" in d
    assert d["model"]["identified_from"].startswith("simulate_plant")
    assert set(d["model"]["kinetic_lag_s"]) == {"heating", "cooling"}
    assert d["observer"]["settings"]["slope_floor_mm_per_k"] > 0


def test_gains_are_per_load_and_go_into_the_session():
    for load in (1.0, 2.0, 4.0):
        d = make("pid", load=load).describe()
        assert d["gains"] == gains_for_load(load).as_dict()
        assert d["ffpid_gains"] == gains_for_load(load, law="ffpid").as_dict()
        assert d["ffpid_hold_gains"] == gains_for_load(load, law="ffpid_hold").as_dict()
        assert d["gains_source"] == f"per-load table ({load:g} kg)"
    tables = {load: gains_for_load(load).as_dict() for load in (1.0, 2.0, 4.0)}
    assert len({tuple(g.values()) for g in tables.values()}) > 1  # not one set for all
    mid = gains_for_load(3.0)  # interpolated between the 2 and 4 kg rows
    lo, hi = sorted((gains_for_load(2.0).kp, gains_for_load(4.0).kp))
    assert lo <= mid.kp <= hi


def test_ceiling_limits_the_temperature():
    c = make("ff", amp=0.8)
    tr = run_closed_loop(c, 2.0, 40.0, dt_s=0.02)
    assert tr.estimate_c.max() <= c.t_ceiling_c + 0.5
    assert math.isfinite(tr.position_mm[-1])


# --------------------------------------------------------------------------- on the mock bench
def test_bench_control_offline_case_settles_every_step_edge():
    """``smabench bench control --offline``: the same case on simulated time, where settling
    does not depend on the machine: PID settles both edges of a 2 kg step."""
    from smabench.bench.control_bench import Case, run_case_offline

    step = run_case_offline(Case("step", "step", 20.0, 1, 2.0, "pid"), 0.0125)
    assert step["settled"] == "2/2" and 0.0 <= step["settle_s"] < 10.0, step
    assert step["samples"] == round(20.0 / 0.0125) + round(8.0 / 0.0125) + 1


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_bench_control_smoke_on_the_mock(tmp_path):
    from smabench.bench.control_bench import Case, format_table, run_case

    # FF+PID's observer needs ≤ 25 ms of device time per tick: 2× speed at 100 Hz gives 20 ms
    # (the benchmark's own 5× at 400 Hz needs a quiet machine; its figures are its own). A 2 s
    # lead-in instead of the benchmark's 8 s: the figures count only after it, and offline they
    # barely move (sine RMS 0.103 → 0.109 mm; step settling 3.7 → 4.5 s, both edges settled)
    sine = Case("sine 10 s", "sine", 10.0, 1, 2.0, "ffpid", lead_in_s=2.0)
    row = run_case(sine, speed=2.0, rate_hz=100.0)
    assert row["samples"] > 100 and 0.0 < row["rms_mm"] < 1.0
    step = run_case(Case("step", "step", 20.0, 1, 2.0, "pid", lead_in_s=2.0), speed=5.0,
                    rate_hz=100.0)  # fmt: skip
    # both step edges settled inside ±2 % of the stroke (offline at this 50 ms device period:
    # 2/2, mean 4.5 s of the 10 s between edges)
    assert step["settled"] == "2/2" and step["settle_s"] < 8.0, step
    text = format_table([row, step])
    assert "RMS mm" in text and "sine 10 s" in text


@pytest.fixture
def run_in_process(cli):
    """``smabench run`` through ``smabench.cli.main`` in this process (no interpreter start; its
    mock still runs in its own process). What it sets for its own process is put back after:
    the SIGTERM handler, and the scheduling of this thread, which ran the loop real-time."""
    handler = signal.getsignal(signal.SIGTERM)
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    yield cli
    signal.signal(signal.SIGTERM, handler)
    os.sched_setscheduler(0, policy, param)


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_run_cli_closed_loop_with_switch(run_in_process, tmp_path):
    run_cli = run_in_process
    # half a sine period after a 2 s lead-in, then FF+PID for the rest (7 s of device time)
    proc = run_cli(
        "run", "--mock", "--mock-speed", "4", "--rate-hz", "100", "--load-kg", "2",
        "--protocol", "sine", "--controller", "pid", "--period-s", "5", "--cycles", "1",
        "--lead-in-s", "2",
        "--switch-at", "4.5:ffpid", "--out", tmp_path, "--session-id", "s", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    from smabench.sessions import load_session

    s = load_session(tmp_path / "s")
    modes = list(s.data["mode"])
    assert modes[0] == "pid" and modes[-1] == "ffpid"
    assert s.meta["controller"]["gains"]["kp"] > 0
    assert np.isfinite(np.asarray(s.data["setpoint_mm"], dtype=float)).all()
    bad = run_cli("run", "--mock", "--load-kg", "2", "--protocol", "sine", "--controller",
                  "pid", "--amplitude-mm", "9", "--out", tmp_path)  # fmt: skip
    assert bad.returncode != 0 and "reachable stroke" in bad.stderr
    assert MODES == ("open_loop", "pid", "ff", "ffpid")


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_run_cli_takes_ffpid_gains_and_stores_them(run_in_process, tmp_path):
    run_cli = run_in_process
    proc = run_cli(
        "run", "--mock", "--mock-speed", "4", "--rate-hz", "100", "--load-kg", "2",
        "--protocol", "step", "--controller", "ffpid", "--period-s", "4", "--cycles", "1",
        "--lead-in-s", "1",
        "--ffpid-gains", "0.2", "1.5", "0", "--ffpid-hold-gains", "0", "0.05", "0",
        "--out", tmp_path, "--session-id", "s", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    from smabench.sessions import load_session

    c = load_session(tmp_path / "s").meta["controller"]
    assert c["ffpid_gains"] == {"kp": 0.2, "ki": 1.5, "kd": 0.0, "d_filter_s": 0.05}
    assert c["ffpid_hold_gains"]["ki"] == 0.05 and c["ffpid_hold_gains_source"] == "settings"
    bad = run_cli("run", "--mock", "--load-kg", "2", "--protocol", "step", "--controller",
                  "ffpid", "--ffpid-hold-gains", "0", "-1", "0", "--out", tmp_path)  # fmt: skip
    assert bad.returncode == 2 and "gain ki must be in 0 … 100" in bad.stderr
