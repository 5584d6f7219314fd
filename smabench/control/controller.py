"""The position controller the bench runtime runs at the loop rate: open loop | PID | FF | FF+PID.

:class:`Controller` is a command source for :class:`~smabench.bench.runtime.BenchRuntime`: each
tick the runtime calls :meth:`Controller.observe` (temperature estimate, ambient, resistance,
position) and :meth:`Controller.update` ``(t_s, position_mm)``, which returns a
:class:`~smabench.commands.CommandStep` with the current, the setpoint (``setpoint_mm``
column) and the active law (``mode`` column).

Laws, all computed in heating power P (W) and sent as ``I = sqrt(P/R)``:

- ``open_loop``: the wrapped open-loop protocol's current when there is one, else the current
  held at its value when open loop was entered (the GUI may set it: :meth:`set_open_loop_current`);
- ``pid``: :class:`~smabench.control.pid.PID` on position, output in W. It keeps one integral per
  direction of the setpoint's motion (the power that holds the wire on the heating branch is
  not the one that holds it on the cooling branch; the direction comes from the reference alone);
- ``ff``: :class:`~smabench.control.feedforward.FeedForward` alone, planning from its own
  heat-balance temperature, with the paper's online adaptation of the loop model (reversal
  points and branch amplitudes from the measured wire);
- ``ffpid``: the feed-forward plus feedback on the remaining error, in two parts.
  A PID in position units (mm/mm, 1/s, s) shifts the setpoint fed to the inverse model: the
  inverse turns the shifted setpoint into temperature and power, hysteresis gap included, so the
  loop the PID sees is close to a unit gain (no gap, no slope changes along the branch). A shift
  back beyond the inverse's reversal deadband reverses the branch, so the PID can undo an
  overshoot by a trip across the gap; within a branch it may slow the wire but not pull it back
  more than ``HOLD_MARGIN_K`` below the hottest (heating) / above the coldest (cooling)
  temperature it reached there. The PID has two gain sets: the tracking gains while the
  setpoint moves, and slow, integral-only hold gains while it stands still (steps, staircases,
  the lead-in): there the feed-forward lands close, and correcting an overshoot means a trip
  across the hysteresis gap that overshoots the other way, so the feedback only trims a steady
  offset. The integral takes the proportional term's change at a gain switch (no step in the
  shift). And a :class:`~smabench.control.observer.TemperatureObserver`
  corrects the temperature the feed-forward plans from and estimates the heat input the heat
  balance misses (latent heat, a wrong convection coefficient …), which the feed-forward's
  power then compensates; the paper's adaptation then also uses the observed temperature.

The output range is ``0 … P_max``: 0 because cooling is passive; ``P_max`` from the current limit
and from a temperature ceiling (the power that would take the estimated temperature above
``t_ceiling_c`` within a step is never commanded, so the runtime's temperature interlock is not
hit by the controller itself).

Switching (:meth:`set_mode`, thread-safe, applied at the start of the next tick; or scripted with
``switches``) is bumpless: the first command of the new law equals the last command. Entering
``pid`` sets the PID integral accordingly; entering ``ff`` or ``ffpid`` synchronises the
feed-forward's temperature (and the observer's) to the runtime's estimate and starts a transfer
offset, the last command minus the new law's, which decays with ``transfer_s``; entering
``open_loop`` holds the last current. The only change at a switch is then the one the new law
makes on its own afterwards.
"""

from __future__ import annotations

import logging
import math
import threading

from smabench.commands import CommandStep
from smabench.control.feedforward import FeedForward
from smabench.control.observer import TemperatureObserver
from smabench.control.pid import PID, PIDGains
from smabench.control.reference import Reference
from smabench.physics.thermal import thermal_constants
from smabench.physics.wire import Wire
from smabench.settings import CONTROLLER_MODES

log = logging.getLogger(__name__)

MODES = CONTROLLER_MODES
"""The controller's modes: the settings schema's choices (declared there once)."""


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

    HOLD_MARGIN_K = 1.0
    TRACK_RATE_MM_S = 5.0  # FF+PID: a setpoint moving faster than this jumped
    FFPID_MAX_PERIOD_S = 0.025  # FF+PID tracks worse at longer loop periods (logged)

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
        ffpid: PID | None = None,
        observer: TemperatureObserver | None = None,
        ffpid_limit_mm: float = 1.0,
        ffpid_hold_gains: PIDGains | None = None,
    ) -> None:
        self.wire = wire
        self.current_limit_a = float(current_limit_a)
        self.reference, self.pid, self.ff = reference, pid, feedforward
        self.ffpid, self.observer = ffpid, observer
        self.ffpid_limit_mm = ffpid_limit_mm
        self.ffpid_hold_gains = ffpid_hold_gains
        self._ffpid_track_gains = ffpid.gains if ffpid is not None else None
        self._last_setpoint: float | None = None
        self._warned_period = False
        self._dt_mean_s = 0.0
        self.open_loop = open_loop
        self.t_ceiling_c = t_ceiling_c
        self.ambient_c = ambient_c
        self.transfer_s = transfer_s
        self.info = dict(info or {})
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.resistance_ohm = wire.resistance_mean_ohm
        self.temperature_c = ambient_c
        if stroke_mm is not None and reference is not None:
            check_reachable(reference.range_mm, stroke_mm, self.info.get("load_kg"))
        self.stroke_mm = stroke_mm
        self._lock = threading.Lock()
        self._pending_mode: str | None = None
        self._pending_gains: dict[str, PIDGains] = {}  # by law, applied at the next tick
        self._pending_open_a: float | None = None
        self._open_set_now = False  # an explicit open-loop current arrived at this tick
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
        self._saturation = 0  # +1: last command at P_max, −1: at 0 W
        self._observed_mm: float | None = None
        self._ext_c = ambient_c  # FF+PID: the wire's hottest / coldest on this branch
        self._hold = 0  # FF+PID: +1 / −1 the PID's pull back is held on heating / cooling

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
        if mode == "pid" and self.pid is None:
            raise ValueError(f"mode {mode!r} needs a PID; none is configured")
        if mode in ("ff", "ffpid") and self.ff is None:
            raise ValueError(f"mode {mode!r} needs the feed-forward model; none is configured")
        if mode == "ffpid" and self.ffpid is None:
            raise ValueError("mode 'ffpid' needs its PID; none is configured")

    def set_mode(self, mode: str) -> None:
        """Switch law at the next tick (bumpless); ValueError if unknown or not configured."""
        self._check_mode(mode)
        with self._lock:
            self._pending_mode = mode

    def set_gains(self, kp: float, ki: float, kd: float, law: str = "pid") -> None:
        """New gains from the next tick for the PID of ``law``: ``pid`` (W/mm, W/(mm·s),
        W·s/mm), ``ffpid`` (tracking) or ``ffpid_hold`` (mm/mm, 1/s, s); the derivative
        filter is kept."""
        if law not in ("pid", "ffpid", "ffpid_hold"):
            raise ValueError(f"gains are for law pid, ffpid or ffpid_hold, got {law!r}")
        pid = self.pid.gains if self.pid is not None else None
        target = {"pid": pid, "ffpid": self._ffpid_track_gains,
                  "ffpid_hold": self.ffpid_hold_gains}[law]  # fmt: skip
        if target is None:
            raise ValueError(f"no PID configured for {law}")
        g = PIDGains(float(kp), float(ki), float(kd), target.d_filter_s)
        g.validate()
        with self._lock:
            self._pending_gains[law] = g

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
            if self.observer is not None:
                self.observer.ambient_c = self.ambient_c
        if resistance_ohm is not None and math.isfinite(resistance_ohm) and resistance_ohm > 0:
            self.resistance_ohm = float(resistance_ohm)
        self._observed_mm = position_mm

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
            gains = self._pending_gains
            if gains:
                self._pending_gains = {}
            open_a, self._pending_open_a = self._pending_open_a, None
        for law, g in gains.items():
            if law == "pid":
                self.pid.set_gains(g)
            elif law == "ffpid_hold":  # FF+PID: the scheduler puts the new set in use
                self.ffpid_hold_gains = g
            else:
                self._ffpid_track_gains = g
                if self.ffpid_hold_gains is None:  # no scheduler: in use at once
                    self.ffpid.set_gains(g)
        self._open_set_now = open_a is not None  # wins over the switch's held current
        if open_a is not None:
            self._open_current_a = open_a
        return mode

    def _plan(
        self, t_s: float, dt: float, mode: str, setpoint: float, position_mm: float,
        p_max: float, entering_ff: bool,
    ) -> tuple[float, float]:  # fmt: skip
        """The inverse model's part of a tick, in every mode (it tracks the reference's
        direction and reversals, which the PID's per-branch integral uses); for ff and ffpid
        also the feed-forward power. Returns (reference temperature °C, power W)."""
        valid = math.isfinite(position_mm)
        uses_ff = mode in ("ff", "ffpid")
        if entering_ff:  # plan from the runtime's estimate, with no heat input yet
            self.ff.sync(self.temperature_c)
            if self.observer is not None:
                self.observer.reset(self.temperature_c, self.ff.inverse.heating)
        heat_w = 0.0
        if mode == "ffpid" and self.observer is not None:
            if not entering_ff:
                self.observer.correct(dt, position_mm, self._saturation, self.temperature_c)
            self.ff.t_ff_c = self.observer.temperature_c
            heat_w = self.observer.disturbance_w
        if self._observed_mm is not None:  # the paper's adaptation: the wire's state
            t_wire = self.ff.t_ff_c if mode == "ffpid" else self.temperature_c
            self.ff.inverse.observe(t_wire, self._observed_mm)
        u_mm = 0.0  # FF+PID: the PID's shift of the setpoint fed to the inverse
        if mode == "ffpid":
            if entering_ff:
                self.ffpid.reset()
                self._last_setpoint = None
            elif valid:
                lim = self.ffpid_limit_mm
                self._schedule_gains(dt, setpoint, position_mm)
                u_mm = self.ffpid.update(dt, setpoint, position_mm, -lim, lim, 0.0,
                                         self._saturation, hold_up=self._hold < 0,
                                         hold_down=self._hold > 0)  # fmt: skip
            else:
                u_mm = self.ffpid.last_output_w
        # the (shifted) setpoint moves the inverse along its branch; moving back beyond the
        # deadband reverses the branch (the feed-forward then crosses the hysteresis gap)
        heating_before = self.ff.inverse.heating
        t_ref = self.ff.reference_temperature(setpoint - u_mm)
        heating = self.ff.inverse.heating
        if heating != heating_before and self.pid is not None:
            # the PID law: the integral that holds the wire on one branch is wrong on the
            # other; each direction of the setpoint's motion keeps its own
            self.pid.branch_integrals[heating_before] = self.pid.integral_w
            self.pid.integral_w = self.pid.branch_integrals[heating]
        if not uses_ff:
            return t_ref, 0.0
        t_follow = self.ff.follow_temperature(t_s, self.reference, -u_mm)
        self._hold = 0
        if mode == "ffpid":
            new_branch = heating != heating_before or entering_ff
            t_follow = self._hold_branch(t_follow, heating, new_branch)
        t_next = min(t_follow, self.ff.cooling_bound(t_s, self.reference, -u_mm))
        t_next = min(max(t_next, self.ambient_c), self.t_ceiling_c)
        return t_ref, self.ff.power(t_next, p_max, heat_w)

    def _schedule_gains(self, dt: float, setpoint: float, position_mm: float) -> None:
        """FF+PID: the tracking gains while the setpoint moves continuously, the hold gains
        while it stands still (or jumps); the integral takes the proportional term's change,
        so the shift does not step."""
        last, self._last_setpoint = self._last_setpoint, setpoint
        if self.ffpid_hold_gains is None:
            return
        rate = 0.0 if last is None else abs(setpoint - last) / dt
        moving = 0.0 < rate <= self.TRACK_RATE_MM_S
        new = self._ffpid_track_gains if moving else self.ffpid_hold_gains
        if new is not self.ffpid.gains:
            if last is not None:
                e = position_mm - setpoint
                self.ffpid.integral_w += (self.ffpid.gains.kp - new.kp) * e
            self.ffpid.gains = new

    def _hold_branch(self, t_follow_c: float, heating: bool, new_branch: bool) -> float:
        """FF+PID: the PID may slow the wire down along its branch but not pull it back more
        than ``HOLD_MARGIN_K`` below the hottest (heating) / above the coldest (cooling)
        temperature it reached on the branch: going back further crosses the hysteresis gap
        (the wire would not move until it came out on the other branch, then overshoot the
        other way: a limit cycle). Sets ``_hold`` (the PID then stops integrating that way)."""
        t_now = self.ff.t_ff_c
        if new_branch:
            self._ext_c = t_now
        self._ext_c = max(self._ext_c, t_now) if heating else min(self._ext_c, t_now)
        if heating and t_follow_c < self._ext_c - self.HOLD_MARGIN_K:
            self._hold = 1
            return self._ext_c - self.HOLD_MARGIN_K
        if not heating and t_follow_c > self._ext_c + self.HOLD_MARGIN_K:
            self._hold = -1
            return self._ext_c + self.HOLD_MARGIN_K
        return t_follow_c

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        dt = self._dt if self._last_t is None else max(t_s - self._last_t, 1e-4)
        self._dt = dt
        self._last_t = t_s
        new_mode = self._apply_pending(t_s)
        switching = not self._entered or (new_mode is not None and new_mode != self._mode)
        if new_mode is not None:
            self._mode = new_mode
        first = not self._entered
        self._entered = True
        mode = self._mode
        self._dt_mean_s += 0.01 * (dt - self._dt_mean_s)  # mean loop period over ~100 ticks
        if (mode == "ffpid" and self._dt_mean_s > self.FFPID_MAX_PERIOD_S
                and not self._warned_period):  # fmt: skip
            self._warned_period = True
            log.warning("FF+PID at a %.0f ms mean loop period: its observer is tuned for ≤ %.0f "
                        "ms and tracks worse; raise the loop rate", self._dt_mean_s * 1e3,
                        self.FFPID_MAX_PERIOD_S * 1e3)  # fmt: skip
        setpoint = done = None
        cycle, phase = 0, mode
        if self.reference is not None:
            setpoint, done = self.reference.update(t_s)
            cycle = self.reference.cycle(t_s)
        valid = math.isfinite(position_mm)
        p_max = self.p_max_w(dt)
        p_last = self.last_current_a**2 * self.resistance_ohm
        uses_ff = mode in ("ff", "ffpid")
        t_ref = None
        p_ff = 0.0
        if self.ff is not None and setpoint is not None:
            entering_ff = uses_ff and (switching or not self._ff_active)
            t_ref, p_ff = self._plan(t_s, dt, mode, setpoint, position_mm, p_max, entering_ff)
            if entering_ff:
                self._transfer_w = 0.0 if first else p_last - p_ff
        self._ff_active = uses_ff
        if switching:
            log.info("t %.2f s: mode %s", t_s, mode)
            self.mode_log.append((t_s, mode))
            if mode == "pid" and valid and not first:
                self.pid.track(setpoint, position_mm, min(p_last, p_max))
            if mode == "open_loop" and not self._open_set_now:
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
        elif mode == "pid":
            if switching and not first:
                power = min(self.pid.last_output_w, p_max)  # the tracked, bumpless output
            elif valid:
                power = self.pid.update(dt, setpoint, position_mm, 0.0, p_max)
            else:  # invalid reading: hold the last command
                power = min(self.last_power_w, p_max)
            current = self._current(power)
        else:  # ff, ffpid: the feed-forward's power plus the decaying transfer offset
            power = min(max(p_ff + self._transfer_w, 0.0), p_max)
            self._transfer_w *= math.exp(-dt / self.transfer_s)
            current = self._current(power)
            if mode == "ffpid" and self.observer is not None:
                self.observer.predict(dt, power)
                self.ff.t_ff_c = self.observer.temperature_c
            else:
                self.ff.advance(dt, power)  # T_ff follows what is really applied
        self._saturation = 1 if power >= p_max - 1e-9 else (-1 if power <= 0.0 else 0)
        self.last_current_a = current
        self.last_power_w = power
        return CommandStep(current, cycle, phase, setpoint, mode, bool(done), power, p_ff, t_ref)

    # ------------------------------------------------------------------ session metadata
    def describe(self) -> dict:
        """What goes into ``session.json``: law, gains, reference, model, adaptation state."""
        d: dict = {"mode": self.mode, **self.info}
        if self.pid is not None:
            d["gains"] = self.pid.gains.as_dict()
        if self.ffpid is not None:
            d["ffpid_gains"] = self._ffpid_track_gains.as_dict()
            if self.ffpid_hold_gains is not None:
                d["ffpid_hold_gains"] = self.ffpid_hold_gains.as_dict()
            d["ffpid_limit_mm"] = self.ffpid_limit_mm
        if self.ff is not None:
            d["feedforward"] = {
                "lead_s": list(self.ff.lead_s),
                "horizon_s": self.ff.horizon_s,
                "preview_slack_s": self.ff.preview_slack_s,
                "t_ceiling_c": self.ff.t_ceiling_c,
                "adapt": self.ff.inverse.adapt,
                "inverse": self.ff.inverse.state(),
            }
        if self.observer is not None:
            d["observer"] = self.observer.state()
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
