"""The position controller the bench runtime runs at the loop rate: open loop | PID | FF | FF+PID.

:class:`Controller` is a command source for :class:`~smabench.bench.runtime.BenchRuntime`: each
tick the runtime calls :meth:`Controller.observe` (temperature estimate, ambient, resistance)
and :meth:`Controller.update` ``(t_s, position_mm)``, which returns a :class:`ControlStep` with
the current, the setpoint (``setpoint_mm`` column) and the active law (``mode`` column).

Laws, all computed in heating power P (W) and sent as ``I = sqrt(P/R)``:

- ``open_loop``: the wrapped open-loop protocol's current when there is one, else the current
  held at its value when open loop was entered (the GUI may set it: :meth:`set_open_loop_current`);
- ``pid``: :class:`~smabench.control.pid.PID` on position;
- ``ff``: :class:`~smabench.control.feedforward.FeedForward` alone;
- ``ffpid``: feed-forward plus PID on the remaining error. The PID's power share P_pid moves the
  feed-forward's temperature target by P_pid/(h·A) — the steady temperature change it stands
  for — and the inverse heat balance makes the power (this path amplifies fast PID changes by
  about τ/dt, hence the low ``ffpid_gain_scale`` and a loop period ≤ 25 ms); ``T_ff`` then
  advances with the total power, so the feed-forward does not cancel the
  PID. The PID gains are scaled by ``ffpid_gain_scale`` on top of the feed-forward.

The output range is ``0 … P_max``: 0 because cooling is passive; ``P_max`` from the current limit
and from a temperature ceiling (the power that would take the estimated temperature above
``t_ceiling_c`` within a step is never commanded, so the runtime's temperature interlock is not
hit by the controller itself).

Switching (:meth:`set_mode`, thread-safe, applied at the start of the next tick; or scripted with
``switches``) is bumpless: entering ``pid``/``ffpid`` sets the PID integral so that the output
equals the last command; entering ``ff`` starts a transfer offset equal to the last command
minus the feed-forward, which decays with ``transfer_s``; entering a law with the feed-forward
synchronises its temperature to the runtime's estimate; entering ``open_loop`` holds the last
current. The only change at a switch is then the one the new law makes on its own afterwards.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass

from smabench.control.feedforward import FeedForward
from smabench.control.pid import PID, PIDGains
from smabench.control.reference import Reference
from smabench.physics.thermal import thermal_constants
from smabench.physics.wire import Wire

log = logging.getLogger(__name__)

MODES = ("open_loop", "pid", "ff", "ffpid")


@dataclass(frozen=True)
class ControlStep:
    current_set_a: float
    cycle: int
    phase: str
    setpoint_mm: float | None
    mode: str
    done: bool = False
    power_w: float = 0.0
    ff_power_w: float = 0.0
    reference_temperature_c: float | None = None


def parse_switch(text: str) -> tuple[float, str]:
    """``S:MODE`` (e.g. ``30:ff``) → (30.0, "ff"); ValueError with the reason otherwise."""
    t, sep, mode = text.partition(":")
    try:
        t_s = float(t)
    except ValueError:
        t_s = math.nan
    if not sep or not math.isfinite(t_s) or t_s < 0:
        raise ValueError(f"--switch-at wants S:MODE with S ≥ 0 seconds, got {text!r}")
    if mode not in MODES:
        raise ValueError(f"--switch-at {text!r}: unknown mode {mode!r}; choose from "
                         f"{', '.join(MODES)}")  # fmt: skip
    return t_s, mode


class Controller:
    """Position controller with live, bumpless switching (see module docstring)."""

    def __init__(
        self,
        wire: Wire,
        current_limit_a: float,
        reference: Reference | None = None,
        pid: PID | None = None,
        feedforward: FeedForward | None = None,
        mode: str = "pid",
        open_loop=None,
        t_ceiling_c: float = 120.0,
        ambient_c: float = 22.0,
        switches: list[tuple[float, str]] | None = None,
        transfer_s: float = 1.0,
        stroke_mm: tuple[float, float] | None = None,
        info: dict | None = None,
        ffpid_gain_scale: float = 1.0,
    ) -> None:
        self.wire = wire
        self.current_limit_a = float(current_limit_a)
        self.reference, self.pid, self.ff = reference, pid, feedforward
        self.open_loop = open_loop
        self.t_ceiling_c = t_ceiling_c
        self.ambient_c = ambient_c
        self.transfer_s = transfer_s
        self.ffpid_gain_scale = ffpid_gain_scale
        self.info = dict(info or {})
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.resistance_ohm = wire.resistance_mean_ohm
        self.temperature_c = ambient_c
        if stroke_mm is not None and reference is not None:
            check_reachable(reference.range_mm, stroke_mm, self.info.get("load_kg"))
        self.stroke_mm = stroke_mm
        self._lock = threading.Lock()
        self._pending_mode: str | None = None
        self._pending_gains: PIDGains | None = None
        self._pending_open_a: float | None = None
        self._check_mode(mode)
        self._mode = mode
        self._entered = False  # first tick enters the initial mode bumplessly from 0 A
        self.switches = sorted(switches or [])
        for _, m in self.switches:
            self._check_mode(m)
        self._last_t: float | None = None
        self._dt = 0.005
        self.last_current_a = 0.0
        self.last_power_w = 0.0
        self._open_current_a = 0.0
        self._transfer_w = 0.0
        self.mode_log: list[tuple[float, str]] = []
        self._ff_active = False
        self._branch_integral = {True: 0.0, False: 0.0}
        self._freeze = 0

    # ------------------------------------------------------------------ thread-safe interface
    @property
    def mode(self) -> str:
        with self._lock:
            return self._pending_mode or self._mode

    def _check_mode(self, mode: str) -> None:
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        if mode == "open_loop":
            return
        if self.reference is None:
            raise ValueError(f"mode {mode!r} needs a position reference; none is configured")
        if mode in ("pid", "ffpid") and self.pid is None:
            raise ValueError(f"mode {mode!r} needs a PID; none is configured")
        if mode in ("ff", "ffpid") and self.ff is None:
            raise ValueError(f"mode {mode!r} needs the feed-forward model; none is configured")

    def set_mode(self, mode: str) -> None:
        """Switch law at the next tick (bumpless); ValueError if unknown or not configured."""
        self._check_mode(mode)
        with self._lock:
            self._pending_mode = mode

    def set_gains(self, kp: float, ki: float, kd: float) -> None:
        """New PID gains from the next tick (the derivative filter is kept)."""
        if self.pid is None:
            raise ValueError("no PID configured")
        g = PIDGains(float(kp), float(ki), float(kd), self.pid.gains.d_filter_s)
        g.validate()
        with self._lock:
            self._pending_gains = g

    def set_open_loop_current(self, current_a: float) -> None:
        """Current held in open-loop mode (when no open-loop protocol is wrapped)."""
        if not 0.0 <= current_a <= self.current_limit_a:
            raise ValueError(f"current {current_a} A outside 0 … {self.current_limit_a} A")
        with self._lock:
            self._pending_open_a = float(current_a)

    # ------------------------------------------------------------------ per tick
    def observe(
        self,
        temperature_c: float,
        ambient_c: float | None = None,
        resistance_ohm: float | None = None,
        position_mm: float | None = None,
    ) -> None:
        """The runtime's estimate this tick (before :meth:`update`)."""
        if math.isfinite(temperature_c):
            self.temperature_c = float(temperature_c)
        if ambient_c is not None and math.isfinite(ambient_c):
            self.ambient_c = float(ambient_c)
            if self.ff is not None:
                self.ff.ambient_c = self.ambient_c
        if resistance_ohm is not None and math.isfinite(resistance_ohm) and resistance_ohm > 0:
            self.resistance_ohm = float(resistance_ohm)
        if self.ff is not None and position_mm is not None:
            self.ff.inverse.observe(self.temperature_c, position_mm)

    def p_max_w(self, dt_s: float) -> float:
        """Largest power: current limit, and no step beyond the temperature ceiling."""
        p_i = self.current_limit_a**2 * self.resistance_ohm
        a = math.exp(-dt_s * self.conductance / self.heat_capacity)
        t_inf = (self.t_ceiling_c - a * self.temperature_c) / (1.0 - a)
        p_t = (t_inf - self.ambient_c) * self.conductance
        return max(0.0, min(p_i, p_t))

    def _current(self, power_w: float) -> float:
        i = math.sqrt(max(power_w, 0.0) / self.resistance_ohm)
        return min(i, self.current_limit_a)

    def _apply_pending(self, t_s: float) -> str | None:
        while self.switches and t_s >= self.switches[0][0]:
            _, m = self.switches.pop(0)
            with self._lock:
                self._pending_mode = m
        with self._lock:
            mode, self._pending_mode = self._pending_mode, None
            gains, self._pending_gains = self._pending_gains, None
            open_a, self._pending_open_a = self._pending_open_a, None
        if gains is not None and self.pid is not None:
            self.pid.set_gains(gains)
        if open_a is not None:
            self._open_current_a = open_a
        return mode

    def update(self, t_s: float, position_mm: float) -> ControlStep:
        dt = self._dt if self._last_t is None else max(t_s - self._last_t, 1e-4)
        self._dt = dt
        self._last_t = t_s
        new_mode = self._apply_pending(t_s)
        switching = not self._entered or (new_mode is not None and new_mode != self._mode)
        if new_mode is not None:
            self._mode = new_mode
        first_tick = not self._entered
        self._entered = True
        mode = self._mode
        setpoint = done = None
        cycle, phase = 0, mode
        if self.reference is not None:
            setpoint, done = self.reference.update(t_s)
            cycle = self.reference.cycle(t_s)
        p_max = self.p_max_w(dt)
        p_last = self.last_current_a**2 * self.resistance_ohm
        uses_ff = mode in ("ff", "ffpid")
        t_ref = None
        t_next = self.ambient_c
        p_ff = 0.0
        if self.ff is not None and setpoint is not None:
            # the inverse tracks the reference (direction, reversals) in every mode
            heating_before = self.ff.inverse.heating
            t_ref = self.ff.reference_temperature(setpoint)
            if self.ff.inverse.heating != heating_before and self.pid is not None:
                # hysteresis: the integral that holds the wire on one branch is wrong on the
                # other; each branch direction keeps its own
                self._branch_integral[heating_before] = self.pid.integral_w
                self.pid.integral_w = self._branch_integral[self.ff.inverse.heating]
            if uses_ff:
                if not self._ff_active:
                    self.ff.sync(self.temperature_c)
                t_next = self.ff.target_temperature(t_s, dt, self.reference)
                p_ff = self.ff.power(dt, t_next, p_max)
        self._ff_active = uses_ff
        if switching:
            log.info("t %.2f s: mode %s", t_s, mode)
            self.mode_log.append((t_s, mode))
            first = len(self.mode_log) == 1
            if self.pid is not None:
                self.pid.gain_scale = self.ffpid_gain_scale if mode == "ffpid" else 1.0
            if mode == "pid" and math.isfinite(position_mm) and not first:
                self.pid.track(setpoint, position_mm, min(p_last, p_max))
            if mode == "ffpid" and math.isfinite(position_mm) and not first:
                # the PID share that makes this tick's power equal the last command
                a = math.exp(-dt * self.conductance / self.heat_capacity)
                t_need = a * self.ff.t_ff_c + (1 - a) * (self.ambient_c + p_last / self.conductance)
                self.pid.track(setpoint, position_mm, (t_need - t_next) * self.conductance)
            if mode == "ff":
                self._transfer_w = 0.0 if first else p_last - p_ff
            if mode == "open_loop":
                self._open_current_a = self.last_current_a
        if mode == "open_loop":
            if self.open_loop is not None:
                step = self.open_loop.update(t_s, position_mm)
                current = float(step.current_set_a)
                phase, cycle = getattr(step, "phase", "open_loop"), step.cycle
                done = bool(getattr(step, "done", False)) or bool(done)
            else:
                current = self._open_current_a
            power = current**2 * self.resistance_ohm
        elif mode == "ff":
            self._transfer_w *= math.exp(-dt / self.transfer_s)
            power = min(max(p_ff + self._transfer_w, 0.0), p_max)
            current = self._current(power)
            self.ff.advance(dt, power)  # T_ff follows what is really applied
        elif mode == "pid":
            if switching and not first_tick:
                power = min(self.pid.last_output_w, p_max)  # the tracked, bumpless output
            elif math.isfinite(position_mm):
                power = self.pid.update(dt, setpoint, position_mm, 0.0, p_max)
            else:  # invalid reading: hold the last command
                power = min(self.last_power_w, p_max)
            current = self._current(power)
        else:  # ffpid: the PID's power share moves the feed-forward's temperature target
            if math.isfinite(position_mm) and not (switching and not first_tick):
                p_pid = self.pid.update(dt, setpoint, position_mm, -p_max, p_max, 0.0,
                                        self._freeze)  # fmt: skip
            else:  # invalid reading, or the switching tick: the tracked (bumpless) share
                p_pid = self.pid.last_output_w
            # the PID share moves the target by the steady temperature change it stands for
            t_target = t_next + p_pid / self.conductance
            power = self.ff.power(dt, min(max(t_target, self.ambient_c), self.t_ceiling_c), p_max)
            self._freeze = 1 if power >= p_max else (-1 if power <= 0.0 else 0)
            current = self._current(power)
            self.ff.advance(dt, power)
        self.last_current_a = current
        self.last_power_w = power
        return ControlStep(current, cycle, phase, setpoint, mode, bool(done), power, p_ff, t_ref)

    # ------------------------------------------------------------------ session metadata
    def describe(self) -> dict:
        """What goes into ``session.json``: law, gains, reference, model, adaptation state."""
        d: dict = {"mode": self.mode, **self.info}
        if self.pid is not None:
            d["gains"] = self.pid.gains.as_dict()
        if self.ff is not None:
            d["feedforward"] = {
                "lead_s": self.ff.lead_s,
                "t_ceiling_c": self.ff.t_ceiling_c,
                "adapt": self.ff.inverse.adapt,
                "inverse": self.ff.inverse.state(),
            }
        if self.stroke_mm is not None:
            d["reachable_mm"] = list(self.stroke_mm)
        d["t_ceiling_c"] = self.t_ceiling_c
        d["mode_log"] = [[t, m] for t, m in self.mode_log]
        return d


def check_reachable(
    setpoints_mm: tuple[float, float], stroke_mm: tuple[float, float], load_kg=None
) -> None:
    """ValueError when a setpoint lies outside the reachable stroke (clear message)."""
    lo, hi = setpoints_mm
    s_lo, s_hi = stroke_mm
    if lo < s_lo - 1e-9 or hi > s_hi + 1e-9:
        under = f" under {load_kg:g} kg" if load_kg is not None else ""
        raise ValueError(
            f"setpoints {lo:.3f} … {hi:.3f} mm are outside the reachable stroke "
            f"{s_lo:.3f} … {s_hi:.3f} mm{under} (position grows with the wire length; the hot "
            "end is the shortest); lower the amplitude or move the offset"
        )
