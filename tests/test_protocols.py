"""Experiment protocols as state machines: timing of heat/cool phases and completion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smabench.protocols import Protocol, ProtocolSettings


def run(settings: ProtocolSettings, position=lambda t: 1.0, dt=0.01, t_max=500.0):
    p = Protocol(settings)
    ts, cur, cyc = [], [], []
    t = 0.0
    while t < t_max:
        step = p.update(t, position(t))
        if step.done:
            break
        ts.append(t)
        cur.append(step.current_set_a)
        cyc.append(step.cycle)
        t += dt
    return np.array(ts), np.array(cur), np.array(cyc), t


def heat_durations(ts, cur):
    on = cur > 0
    edges = np.flatnonzero(np.diff(on.astype(int)))
    starts = [0] if on[0] else []
    starts += [e + 1 for e in edges if not on[e]]
    ends = [e + 1 for e in edges if on[e]]
    return [ts[e] - ts[s] for s, e in zip(starts, ends, strict=False)]


def test_complete_cycles_wait_for_settling():
    s = ProtocolSettings(
        name="cycles",
        cycles=3,
        current_a=1.2,
        heat_s=2.0,
        min_cool_s=1.0,
        cool_timeout_s=20.0,
        settle_window_s=1.0,
        settle_mm=0.01,
    )
    ts, cur, cyc, t_end = run(s, position=lambda t: 1.0)
    assert heat_durations(ts, cur) == pytest.approx([2.0, 2.0, 2.0], abs=0.02)
    assert set(cur) == {0.0, 1.2} and cyc.max() == 2
    # constant position settles after the min cooling time: each cycle ≈ 2 + 1 s
    assert t_end == pytest.approx(9.0, abs=0.1)


def test_cooling_times_out_when_position_keeps_moving():
    s = ProtocolSettings(name="cycles", cycles=1, heat_s=1.0, cool_timeout_s=5.0)
    _, _, _, t_end = run(s, position=lambda t: 0.1 * t)
    assert t_end == pytest.approx(6.0, abs=0.05)
    # an exponential relaxation settles (spread < 5 µm over 1 s) about 5.3 s into cooling
    s = ProtocolSettings(name="cycles", cycles=1, heat_s=1.0, cool_timeout_s=30.0)
    _, _, _, t_end = run(s, position=lambda t: 2.0 - math.exp(-max(t - 1.0, 0.0)))
    assert 1.0 + 5.0 < t_end < 1.0 + 6.5


def wire(t_off_s: float, plateau_s: float, cold_mm: float = 2.6, hot_mm: float = 0.1):
    """A wire's position: contracts while heated from t = 0 to ``t_off_s`` (τ 0.2 s), then holds
    at ``hot_mm`` for ``plateau_s`` as it cools down to Ms, then stretches back (τ 0.5 s)."""

    def position(t: float) -> float:
        if t < t_off_s:
            return hot_mm + (cold_mm - hot_mm) * math.exp(-t / 0.2)
        back = t - t_off_s - plateau_s
        return hot_mm if back < 0 else cold_mm - (cold_mm - hot_mm) * math.exp(-back / 0.5)

    return position


def test_cooling_waits_for_the_wire_to_stretch_back_not_the_hot_plateau():
    """After the current stops the wire stays contracted, still and still hot, until it has
    cooled to Ms: settling there would reheat before the reverse transformation (a partial
    cycle in a session called complete). Cooling ends once the wire has stretched back and
    settled; the sample mock sessions show a 3 s plateau (1.4 A, 3 s, 1 kg)."""
    s = ProtocolSettings(name="cycles", cycles=1, heat_s=3.0, min_cool_s=3.0,
                         cool_timeout_s=30.0)  # fmt: skip
    _, _, _, t_end = run(s, position=wire(3.0, plateau_s=4.0))
    # stretched back from 7 s on; within 5 µm of its mean drift about 3.5 s later
    assert 3.0 + 4.0 + 2.0 < t_end < 3.0 + 4.0 + 5.0, t_end
    # a wire that never contracted (no stroke to recover) still settles after min_cool_s
    _, _, _, t_end = run(s, position=lambda t: 1.0)
    assert t_end == pytest.approx(3.0 + 3.0, abs=0.1)


def test_incomplete_reheats_early_and_inner_uses_short_pulses():
    s = ProtocolSettings(
        name="incomplete", cycles=3, heat_s=2.0, partial_cool_s=1.5, min_cool_s=1.0
    )
    ts, cur, _, t_end = run(s)
    assert heat_durations(ts, cur) == pytest.approx([2.0, 2.0, 2.0], abs=0.02)
    assert t_end == pytest.approx(2 * 3.5 + 3.0, abs=0.1)
    s = ProtocolSettings(
        name="inner", cycles=4, heat_s=3.0, inner_heat_s=0.5, inner_cool_s=0.7, min_cool_s=1.0
    )
    ts, cur, _, _ = run(s)
    assert heat_durations(ts, cur) == pytest.approx([3.0, 0.5, 0.5, 0.5], abs=0.02)


def test_step_and_ramp():
    s = ProtocolSettings(name="step", levels_a=(0.5, 1.0, 0.0), hold_s=2.0)
    ts, cur, _, t_end = run(s)
    assert t_end == pytest.approx(6.0, abs=0.02)
    assert cur[ts < 1.9].max() == 0.5 and cur[(ts > 2.1) & (ts < 3.9)].min() == 1.0
    s = ProtocolSettings(name="ramp", cycles=2, current_a=1.0, ramp_s=1.0)
    ts, cur, _, t_end = run(s, dt=0.001)
    assert cur.max() == pytest.approx(1.0, abs=1e-2) and t_end == pytest.approx(4.0, abs=0.01)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "zigzag"}, "unknown protocol 'zigzag'; choose from cycles, incomplete"),
        ({"current_a": 3.0}, r"current must be in 0 … 2.5 A, got 3 A \(protocol.current_a\)"),
        ({"current_a": -0.1}, r"current must be in 0 … 2.5 A, got -0.1 A"),
        ({"current_a": 2.1}, "current 2.1 A is outside 0 … 2 A, the current limit"),
        ({"name": "step", "levels_a": (0.5, 2.2)}, r"current levels 2.2 A is outside 0 … 2 A"),
        ({"cycles": 0}, r"cycles must be in 1 … 10000, got 0 \(protocol.cycles\)"),
        ({"cycles": 2.5}, "cycles must be a whole number"),
        ({"heat_s": 0}, r"heat time must be in \(0, 600\] s, got 0 s \(protocol.heat_s\)"),
        ({"settle_window_s": math.inf}, "settle window must be in"),
    ],
)
def test_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ProtocolSettings(**kwargs).validate(max_current_a=2.0)


def test_only_the_protocols_own_currents_are_bounded_by_the_limit():
    # a ramp at 1.5 A under a 1 A limit is refused; the same current on a step protocol (which
    # runs its levels) is not the step's business
    with pytest.raises(ValueError, match="outside 0 … 1 A"):
        ProtocolSettings(name="ramp", current_a=1.5).validate(max_current_a=1.0)
    ProtocolSettings(name="step", current_a=1.5, levels_a=(0.5, 1.0)).validate(max_current_a=1.0)
    ProtocolSettings(name="sine", current_a=2.4).validate(max_current_a=1.0, closed_loop=True)
