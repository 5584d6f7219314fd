"""Campaigns: a test plan (TOML) of steps run unattended, resumable after a crash.

A plan file has a ``[plan]`` table (name, wire, loop rate, limits, where the sessions go) and
``[[step]]`` tables (protocol, load, cycles, currents, times, a rest after). :data:`PLAN_SCHEMA`
and :data:`STEP_SCHEMA` list every key; a key that is a run setting is that setting
(:func:`setting_key`: type, range, unit, default and help from :mod:`smabench.settings`), the
plan's own (name, retries, rest) are declared here; anything else is refused with the key
named. ``smabench plan run PLAN --dry-run`` prints each step's duration (an upper bound:
cooling until its timeout), peak current, predicted peak wire temperature (the plant's heat
balance, every cooling at its shortest) and Joule energy in the wire, and checks every
step against the limits exactly as ``smabench run`` would (nothing is opened); a step whose
predicted peak exceeds ``temperature_limit_c`` or that may outlast ``max_step_s`` is refused.

Running: each step is one session (``smabench.bench.session_run.run_session`` on devices opened
as ``smabench run`` does, the mock bench started per step with the step's load). Before a step
whose load differs from the one hanging, the operator is asked on the terminal to change it.
A state file ``plan-state.json`` beside the sessions (written atomically before and after every
step) records each step's status and session; ``smabench plan resume STATE`` continues at the
first unfinished step after a crash or a power loss (a step cut short is run again as a new
session, the interrupted one kept and linked). Only a lost device link is run again unattended
(``retries``); an interlock or the driver's safety trip (over-temperature or energy, over-current,
open wire, e-stop, lease) ends the plan with the step ``tripped``, and ``resume`` asks first
(``--yes``; refused with one line when nobody answers). Each session's ``session.json`` gets a
``plan`` entry (plan name, step, index, the previous session), so the sessions of a campaign are
linked.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from smabench import settings
from smabench.sessions import META_FILE, atomic_write_json, close_dead_session, write_meta

log = logging.getLogger(__name__)

STATE_FILE = "plan-state.json"
STATE_FORMAT = "smabench-plan-state/1"
PLAN_PROTOCOLS = ("cycles", "incomplete", "inner")
RETRIED_CAUSES = ("device",)
"""Session end causes (``smabench.bench.tick.CAUSES``) a plan may run again unattended: link
losses only. Every other abort (interlock, safety trip, e-stop) ends the plan."""


@dataclass(frozen=True)
class Key:
    """One declared key: Python type, range (inclusive), unit, help; ``required`` or default.
    With ``setting``, a run setting's key (:data:`smabench.settings.SETTINGS`): its type, help,
    unit and default come from there and its range is checked there (:func:`setting_key`)."""

    type: type
    help: str
    unit: str = ""
    low: float | None = None
    high: float | None = None
    default: Any = None
    required: bool = False
    choices: tuple[str, ...] | None = None
    setting: str | None = None


_KIND_TYPES: dict[str, type] = {"float": float, "int": int, "bool": bool, "choice": str,
                                "text": str}  # fmt: skip


def setting_key(key: str, *, required: bool = False,
                choices: tuple[str, ...] | None = None) -> Key:  # fmt: skip
    """The plan key that is the run setting ``key``: declared once, in :mod:`smabench.settings`
    (a plan step runs as ``smabench run`` would, so it takes what ``run`` takes: the plan's own
    ranges had let a dry run pass 10⁶ cycles that the step's session then refused)."""
    s = settings.get(key)
    return Key(_KIND_TYPES[s.kind], s.help, s.unit, default=None if required else s.default,
               required=required, choices=choices, setting=key)  # fmt: skip


PLAN_SCHEMA: dict[str, Key] = {
    "name": Key(str, "plan name (folder of its sessions)", required=True),
    "wire": setting_key("wire_preset"),
    "rate_hz": setting_key("rate_hz"),
    "current_limit_a": setting_key("current_limit_a"),
    "temperature_limit_c": setting_key("temperature_limit_c"),
    "max_step_s": setting_key("max_duration_s"),
    "allow_high_stress": setting_key("allow_high_stress"),
    "out": setting_key("out_dir"),
    "mock_speed": setting_key("time_scale"),
    "retries": Key(int, "times a step that lost a device link (never a safety trip or an "
                   "interlock) is run again unattended, as a new session", "", 0, 10, default=1),
}
STEP_SCHEMA: dict[str, Key] = {
    "name": Key(str, "step name (unique in the plan)", required=True),
    "protocol": setting_key("protocol.name", required=True, choices=PLAN_PROTOCOLS),
    "load_kg": setting_key("load_kg", required=True),
    "cycles": setting_key("protocol.cycles"),
    "current_a": setting_key("protocol.current_a"),
    "heat_s": setting_key("protocol.heat_s"),
    "cool_timeout_s": setting_key("protocol.cool_timeout_s"),
    "min_cool_s": setting_key("protocol.min_cool_s"),
    "partial_cool_s": setting_key("protocol.partial_cool_s"),
    "inner_heat_s": setting_key("protocol.inner_heat_s"),
    "inner_cool_s": setting_key("protocol.inner_cool_s"),
    "rest_s": Key(float, "rest with the output off after the step", "s", 0.0, 86400.0,
                  default=0.0),  # fmt: skip
}


class PlanError(ValueError):
    """A plan or state file that cannot be used (message names file, step and key)."""


def _check_table(table: dict[str, Any], schema: dict[str, Key], where: str) -> dict[str, Any]:
    unknown = sorted(set(table) - set(schema))
    if unknown:
        raise PlanError(f"{where}: unknown key(s) {', '.join(unknown)} "
                        f"(known: {', '.join(schema)})")  # fmt: skip
    out: dict[str, Any] = {}
    for name, key in schema.items():
        if name not in table:
            if key.required:
                raise PlanError(f"{where}: missing {name} ({key.help})")
            out[name] = key.default
            continue
        v = table[name]
        if key.type is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, key.type) or (key.type is not bool and isinstance(v, bool)):
            raise PlanError(f"{where}: {name} must be {key.type.__name__}, got {v!r}")
        if key.choices and v not in key.choices:
            raise PlanError(f"{where}: {name} {v!r} is not one of {', '.join(key.choices)}")
        if key.low is not None and not (key.low <= v <= key.high):
            raise PlanError(f"{where}: {name} = {v} is out of range [{key.low:g}, {key.high:g}] "
                            f"{key.unit}".rstrip())  # fmt: skip
        if key.setting is not None:
            try:
                v = settings.check_value(key.setting, v)
            except settings.SettingError as exc:
                raise PlanError(f"{where}: {exc.naming(name)}") from None
        out[name] = v
    return out


@dataclass
class Plan:
    path: Path
    settings: dict[str, Any]
    steps: list[dict[str, Any]]
    sha256: str

    @property
    def folder(self) -> Path:
        out = Path(self.settings["out"])
        if not out.is_absolute():
            out = Path.cwd() / out
        return out / self.settings["name"]


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan file (:class:`PlanError` naming the first problem)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        doc = tomllib.loads(raw.decode("utf-8"))
    except OSError as exc:
        raise PlanError(f"cannot read {path}: {exc.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PlanError(f"{path}: not valid TOML ({exc})") from None
    unknown = sorted(set(doc) - {"plan", "step"})
    if unknown:
        raise PlanError(f"{path}: unknown table(s) {', '.join(unknown)} (use [plan] and [[step]])")
    if not isinstance(doc.get("plan"), dict):
        raise PlanError(f"{path}: no [plan] table")
    settings = _check_table(doc["plan"], PLAN_SCHEMA, f"{path} [plan]")
    steps_raw = doc.get("step")
    if not isinstance(steps_raw, list) or not steps_raw:
        raise PlanError(f"{path}: no [[step]] tables")
    steps = []
    for i, st in enumerate(steps_raw, start=1):
        steps.append(_check_table(st, STEP_SCHEMA, f"{path} step {i}"))
    names = [s["name"] for s in steps]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise PlanError(f"{path}: step names must be unique ({', '.join(dup)})")
    plan = Plan(path, settings, steps, hashlib.sha256(raw).hexdigest())
    for i, st in enumerate(steps, start=1):
        try:
            run_settings(plan, st).validate()
        except ValueError as exc:
            raise PlanError(f"{path} step {i} ({st['name']}): {exc}") from None
        check_step_limits(plan, i, st)
    return plan


def run_settings(plan: Plan, step: dict[str, Any], session_id: str | None = None,
                 time_scale: float = 1.0):  # fmt: skip
    """The ``RunSettings`` of one step (what ``smabench run`` would build)."""
    from smabench.bench.session_run import RunSettings
    from smabench.protocols import ProtocolSettings

    proto = ProtocolSettings(
        name=step["protocol"], cycles=step["cycles"], current_a=step["current_a"],
        heat_s=step["heat_s"], cool_timeout_s=step["cool_timeout_s"],
        min_cool_s=min(step["min_cool_s"], step["cool_timeout_s"]),
        partial_cool_s=step["partial_cool_s"], inner_heat_s=step["inner_heat_s"],
        inner_cool_s=step["inner_cool_s"],
    )  # fmt: skip
    ps = plan.settings
    return RunSettings(
        load_kg=step["load_kg"], protocol=proto, rate_hz=ps["rate_hz"], wire_preset=ps["wire"],
        current_limit_a=ps["current_limit_a"], temperature_limit_c=ps["temperature_limit_c"],
        max_duration_s=ps["max_step_s"], out_dir=plan.folder, session_id=session_id,
        time_scale=time_scale, allow_high_stress=ps["allow_high_stress"],
    )  # fmt: skip


# --------------------------------------------------------------------------- dry run
def step_budget(plan: Plan, step: dict[str, Any]) -> dict[str, float]:
    """Upper-bound duration (s), peak current (A) and Joule energy in the wire (J) of a step."""
    from smabench.physics.wire import PRESETS

    r_ohm = PRESETS[plan.settings["wire"]].resistance_ohm(0.0)  # martensite: the larger R
    i = step["current_a"]
    n = step["cycles"]
    if step["protocol"] == "cycles":
        heat, cool = step["heat_s"], step["cool_timeout_s"]
        on_s = n * heat
    elif step["protocol"] == "incomplete":
        heat, cool = step["heat_s"], step["partial_cool_s"] + step["cool_timeout_s"]
        on_s = n * heat * 2  # heat, partial cool, reheat: at most two heatings per cycle
        heat *= 2
    else:  # inner: a full heating then pulses; bounded by heat + pulses within the cooling
        heat, cool = step["heat_s"], step["cool_timeout_s"]
        duty = step["inner_heat_s"] / (step["inner_heat_s"] + step["inner_cool_s"])
        on_s = n * (heat + duty * cool)
    duration = n * (heat + cool) + step["rest_s"]
    return {"duration_s": duration, "peak_current_a": i, "energy_j": i * i * float(r_ohm) * on_s}


PEAK_AMBIENT_C = 22.0
"""Room temperature of the dry run's peak prediction, °C (the plant's and the mock's)."""
PEAK_MAX_CYCLES = 10_000
"""Cycles followed for the peak: the ratchet of a short cooling converges long before."""


def _phases(step: dict[str, Any]) -> list[tuple[float, float]]:
    """One cycle of the step at its hottest, as (duration s, current A): the shortest cooling
    the protocol allows (``min_cool_s``; settling may end a cooling then), every reheating."""
    i = step["current_a"]
    cool = min(step["min_cool_s"], step["cool_timeout_s"])
    if step["protocol"] == "cycles":
        return [(step["heat_s"], i), (cool, 0.0)]
    if step["protocol"] == "incomplete":
        return [(step["heat_s"], i), (step["partial_cool_s"], 0.0), (step["heat_s"], i),
                (cool, 0.0)]  # fmt: skip
    pulses = max(1, int(step["cool_timeout_s"] // (step["inner_heat_s"] + step["inner_cool_s"])))
    return [(step["heat_s"], i),
            *[(d, c) for _ in range(pulses)
              for d, c in ((step["inner_cool_s"], 0.0), (step["inner_heat_s"], i))],
            (cool, 0.0)]  # fmt: skip


def predicted_peak_c(plan: Plan, step: dict[str, Any]) -> float:
    """The step's peak wire temperature, °C, predicted with the plant's heat balance
    (:func:`smabench.physics.thermal.step_exact`, exact per phase) at the martensite's larger
    resistance, from :data:`PEAK_AMBIENT_C`, every cooling at its shortest: an upper bound of
    what the host's estimate (the same heat balance) will show, so a step that passes here does
    not trip the temperature interlock on a nominal wire."""
    from smabench.physics.thermal import step_exact
    from smabench.physics.wire import PRESETS

    wire = PRESETS[plan.settings["wire"]]
    r_ohm = float(wire.resistance_ohm(0.0))
    temp = peak = PEAK_AMBIENT_C
    phases = _phases(step)
    for _ in range(min(step["cycles"], PEAK_MAX_CYCLES)):
        before = temp
        for duration_s, current_a in phases:
            temp = float(step_exact(temp, current_a, duration_s, wire, PEAK_AMBIENT_C, r_ohm))
            peak = max(peak, temp)  # a heating phase peaks at its end
        if abs(temp - before) < 1e-3:  # the cycle repeats itself: so does its peak
            break
    return peak


def check_step_limits(plan: Plan, index: int, step: dict[str, Any]) -> None:
    """PlanError when the step's predicted peak exceeds the temperature limit or its
    upper-bound duration exceeds ``max_step_s`` (it would trip or be aborted)."""
    ps = plan.settings
    where = f"{plan.path} step {index} ({step['name']})"
    peak = predicted_peak_c(plan, step)
    if peak > ps["temperature_limit_c"]:
        raise PlanError(f"{where}: predicted peak wire temperature {peak:.0f} °C exceeds "
                        f"temperature_limit_c {ps['temperature_limit_c']:g} °C: lower current_a "
                        "or heat_s, or cool longer")  # fmt: skip
    b = step_budget(plan, step)
    active_s = b["duration_s"] - step["rest_s"]  # the session; the rest is outside it
    if active_s > ps["max_step_s"]:
        raise PlanError(f"{where}: takes up to {active_s:.0f} s, longer than max_step_s "
                        f"{ps['max_step_s']:g} s (it would be aborted): fewer cycles, or raise "
                        "max_step_s")  # fmt: skip


def dry_run(plan: Plan) -> list[str]:
    """The dry-run report (lines); the plan is already checked against the limits."""
    lines = [f"plan {plan.settings['name']} ({plan.path}): {len(plan.steps)} step(s), "
             f"sessions in {plan.folder}"]  # fmt: skip
    total = energy = 0.0
    peak = 0.0
    load = None
    lines.append(f"{'#':>3} {'step':16s} {'protocol':10s} {'load kg':>7s} {'stress MPa':>10s} "
                 f"{'cycles':>6s} {'I A':>5s} {'peak °C':>7s} {'≤ time':>9s} "
                 f"{'energy J':>9s}")  # fmt: skip
    hottest = 0.0
    for i, st in enumerate(plan.steps, start=1):
        b = step_budget(plan, st)
        peak_c = predicted_peak_c(plan, st)
        hottest = max(hottest, peak_c)
        stress = run_settings(plan, st).stress()
        total += b["duration_s"]
        energy += b["energy_j"]
        peak = max(peak, b["peak_current_a"])
        change = "  ← load change (operator)" if load is not None and st["load_kg"] != load else ""
        load = st["load_kg"]
        lines.append(
            f"{i:>3} {st['name'][:16]:16s} {st['protocol']:10s} {st['load_kg']:7.3g} "
            f"{stress.stress_mpa:10.0f} {st['cycles']:6d} {st['current_a']:5.2f} "
            f"{peak_c:7.0f} {_hms(b['duration_s']):>9s} {b['energy_j']:9.1f}{change}"
        )
    lines.append(f"total ≤ {_hms(total)} (cooling to its timeout; at --mock speed "
                 f"{plan.settings['mock_speed']:g}×: ≤ {_hms(total / plan.settings['mock_speed'])}"
                 f"), peak current {peak:.2f} A (limit {plan.settings['current_limit_a']:g} A), "
                 f"energy {energy:.0f} J")  # fmt: skip
    lines.append(f"limits: every step checked as smabench run would (current, load, stress), "
                 f"predicted peak ≤ {hottest:.0f} °C (limit "
                 f"{plan.settings['temperature_limit_c']:g} °C), each within max_step_s "
                 f"{plan.settings['max_step_s']:g} s: ok")  # fmt: skip
    return lines


def _hms(s: float) -> str:
    s = int(math.ceil(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


# --------------------------------------------------------------------------- state
def new_state(plan: Plan) -> dict[str, Any]:
    return {
        "format": STATE_FORMAT,
        "plan": str(plan.path.resolve()),
        "plan_sha256": plan.sha256,
        "name": plan.settings["name"],
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "loaded_kg": None,
        "steps": [{"name": s["name"], "status": "pending", "session": None, "interrupted": []}
                  for s in plan.steps],  # fmt: skip
    }


def save_state(folder: Path, state: dict[str, Any]) -> Path:
    state["updated_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return atomic_write_json(folder / STATE_FILE, state)


def load_state(path: str | Path) -> tuple[dict[str, Any], Path]:
    """A state file, or a plan folder holding one → (state, folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / STATE_FILE
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise PlanError(f"cannot read {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise PlanError(f"{path}: invalid JSON ({exc.msg})") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise PlanError(f"{path}: not a plan state file ({STATE_FORMAT})")
    return state, path.parent


# --------------------------------------------------------------------------- running
@dataclass
class Devices:
    """How steps reach the bench: the mock (started per step) or ports."""

    mock: bool = False
    port: str | None = None
    sensor: str | None = None
    sensor_map: str = "generic-rs485-laser"


def ask_load(load_kg: float, previous: float | None, step: str) -> bool:
    """Ask the operator to change the load; True when confirmed (Enter), False to stop."""
    print(f"\n>>> step {step}: change the load from {previous:g} kg to {load_kg:g} kg, "
          "then press Enter (or type 'stop' and Enter to stop here; resume later)", flush=True)
    line = sys.stdin.readline()
    if not line:  # EOF: nobody at the terminal
        print("no operator input (end of input): stopping before the load change", flush=True)
        return False
    return line.strip().lower() not in ("stop", "s", "q", "quit", "abort")


def asker(prompt: str = "auto") -> Callable[[float, float | None, str], bool]:
    """The load-change prompt: ``gui`` a dialog, ``terminal`` :func:`ask_load`, ``auto`` the
    dialog when a display is available."""
    if prompt == "terminal":
        return ask_load
    from smabench.gui.plan_prompt import ask_load_dialog, display_available

    if prompt == "gui" or display_available():
        return ask_load_dialog
    return ask_load


def _run_step_session(plan: Plan, step: dict[str, Any], sid: str, dev: Devices) -> tuple[Path, Any]:
    from smabench.bench.headless import MockProcess, open_devices
    from smabench.bench.session_run import run_session
    from smabench.protocols import Protocol

    scale = plan.settings["mock_speed"] if dev.mock else 1.0
    settings = run_settings(plan, step, sid, time_scale=scale)
    settings.validate()
    mock = None
    source = sensor = None
    try:
        if dev.mock:
            mock_args = ["--load-kg", f"{step['load_kg']:g}", "--speed", f"{scale:g}"]
            mock = MockProcess(mock_args)
            port, spec = mock.ports.driver, mock.ports.sensor_tcp
        else:
            port, spec = dev.port, dev.sensor
        source, sensor = open_devices(port, spec, settings, dev.sensor_map)
        devices = {"current_driver": {"port": port, **dataclasses.asdict(source.info)},
                   "sensor": {"spec": spec, "map": sensor.map.name},
                   "mock": mock_args if dev.mock else None}  # fmt: skip
        return run_session(settings, source, sensor, devices, command=Protocol(settings.protocol))
    finally:
        for d in (source, sensor):
            if d is not None:
                with contextlib.suppress(Exception):
                    d.make_safe()
                with contextlib.suppress(Exception):
                    d.close()
        if mock is not None:
            mock.close()


def _link_session(folder: Path, link: dict[str, Any]) -> None:
    meta_path = folder / META_FILE
    with contextlib.suppress(OSError, json.JSONDecodeError):
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        meta["plan"] = link
        write_meta(folder, meta)


def execute(
    plan: Plan,
    state: dict[str, Any],
    dev: Devices,
    ask: Callable[[float, float | None, str], bool] = ask_load,
    sleep: Callable[[float], None] = time.sleep,
    assume_loaded: bool = False,
) -> int:
    """Run the plan's unfinished steps in order; returns 0 when all are done, 1 when a step did
    not complete, 3 when the operator stopped at a load change. The state is saved before and
    after every step, so a crash at any point leaves a state to resume from."""
    folder = plan.folder
    folder.mkdir(parents=True, exist_ok=True)
    save_state(folder, state)
    print(f"plan state: {folder / STATE_FILE}", flush=True)
    prev_session = next((s["session"] for s in reversed(state["steps"]) if s["session"]), None)
    for i, (st, entry) in enumerate(zip(plan.steps, state["steps"], strict=True), start=1):
        if entry["status"] == "done":
            continue
        if entry["session"]:  # cut short by a crash, or failed: kept, linked, run anew
            if Path(entry["session"]).is_dir():  # killed: its session.json says so from now on
                was, why = close_dead_session(entry["session"])
                print(f"{st['name']}: its last session {Path(entry['session']).name} {was}: "
                      f"{why}", flush=True)  # fmt: skip
            entry["interrupted"].append(entry["session"])
            entry["session"] = None
        loaded = state.get("loaded_kg")
        change = loaded is not None and loaded != st["load_kg"] and not assume_loaded
        if change and not ask(st["load_kg"], loaded, st["name"]):
            entry["status"] = "pending"
            save_state(folder, state)
            return 3
        state["loaded_kg"] = st["load_kg"]
        attempt = len(entry["interrupted"])
        sid = f"{i:02d}-{st['name']}" + (f"-r{attempt}" if attempt else "")
        entry.update(status="running", session=str(folder / sid),
                     started_at=time.strftime("%Y-%m-%dT%H:%M:%S%z"))  # fmt: skip
        save_state(folder, state)
        print(f"step {i}/{len(plan.steps)} {st['name']}: {st['protocol']}, {st['cycles']} "
              f"cycle(s) at {st['current_a']:g} A under {st['load_kg']:g} kg", flush=True)
        while True:
            try:
                session, result = _run_step_session(plan, st, sid, dev)
            except KeyboardInterrupt:
                entry["status"] = "running"  # resumable: run again as a new session
                save_state(folder, state)
                raise
            retried = entry.setdefault("retried", 0)
            # only a link loss is run again; an interlock, the driver's safety trip (energy,
            # over-temperature, over-current, open wire, e-stop, lease), a broken wire or the
            # operator end the plan (RunResult.cause, smabench.bench.tick.CAUSES)
            if (result.status != "aborted" or result.cause not in RETRIED_CAUSES
                    or retried >= plan.settings["retries"]):  # fmt: skip
                break
            # a link loss (driver telemetry or sensor lost): run the step again
            print(f"  {result.status}: {result.reason}; running the step again "
                  f"({retried + 1} of {plan.settings['retries']})", flush=True)  # fmt: skip
            _link_session(session, {"name": plan.settings["name"], "step": st["name"],
                                    "index": i, "state_file": str(folder / STATE_FILE),
                                    "superseded": True})  # fmt: skip
            entry["retried"] = retried + 1
            entry["interrupted"].append(str(session))
            sid = f"{i:02d}-{st['name']}-r{len(entry['interrupted'])}"
            entry["session"] = str(folder / sid)
            save_state(folder, state)
        _link_session(session, {"name": plan.settings["name"], "step": st["name"], "index": i,
                                "state_file": str(folder / STATE_FILE),
                                "previous_session": prev_session,
                                "interrupted_sessions": entry["interrupted"]})  # fmt: skip
        prev_session = str(session)
        entry.update(status="done" if result.status == "completed" else "failed",
                     result=f"{result.status}: {result.reason}",
                     ended_at=time.strftime("%Y-%m-%dT%H:%M:%S%z"))  # fmt: skip
        save_state(folder, state)
        print(f"  {result.status}: {result.reason} ({result.samples} samples) → {session}",
              flush=True)  # fmt: skip
        if result.status != "completed" and result.cause in RETRIED_CAUSES:
            print(f"smabench plan: step {st['name']} {result.status}: {result.reason}; "
                  f"fix and `smabench plan resume {folder}`", file=sys.stderr)  # fmt: skip
            entry["status"] = "pending"
            save_state(folder, state)
            return 1
        if result.status != "completed":  # a safety trip: never run again unattended
            entry.update(status="tripped", cause=result.cause)
            save_state(folder, state)
            print(f"smabench plan: step {st['name']} stopped by a safety trip ({result.reason}); "
                  f"the plan ends here and the step is not run again: check the bench, then "
                  f"`smabench plan resume {folder}` asks before continuing",
                  file=sys.stderr)  # fmt: skip
            return 1
        if st["rest_s"] > 0:
            rest = st["rest_s"] / (plan.settings["mock_speed"] if dev.mock else 1.0)
            print(f"  rest {rest:g} s (output off)", flush=True)
            sleep(rest)
    print(f"plan {plan.settings['name']}: all {len(plan.steps)} step(s) done", flush=True)
    return 0


# --------------------------------------------------------------------------- CLI
def _devices(args: argparse.Namespace) -> Devices:
    if args.mock == bool(args.port):
        raise PlanError("give either --mock or --port DEV --sensor SPEC")
    if args.port and not args.sensor:
        raise PlanError("--port needs --sensor (tcp:HOST:PORT or rtu:DEVICE[:BAUD])")
    if args.mock:
        from smabench.bench.headless import ready_timeout_s

        ready_timeout_s()  # its environment setting checked before anything runs
    port = args.port
    if port:
        from smabench.drivers.link import stable_port_name

        # every step and every retry opens the adapter's stable name: after a replug it is
        # back under another device name, and the old name may be another device's
        stable = stable_port_name(port)
        if stable is not None:
            print(f"port {port}: the steps open its stable name {stable}", flush=True)
            port = stable
    return Devices(args.mock, port, args.sensor, args.sensor_map)


def cmd_plan_run(args: argparse.Namespace) -> int:
    plan = load_plan(args.plan)
    if args.dry_run:
        for line in dry_run(plan):
            print(line)
        return 0
    dev = _devices(args)
    state_path = plan.folder / STATE_FILE
    if state_path.exists():
        raise PlanError(f"{state_path} exists: `smabench plan resume {plan.folder}` continues "
                        "it (or move it away to start again)")  # fmt: skip
    for line in dry_run(plan):
        print(line)
    return execute(plan, new_state(plan), dev, ask=asker(args.prompt),
                   assume_loaded=args.assume_loaded)  # fmt: skip


def cmd_plan_resume(args: argparse.Namespace) -> int:
    state, folder = load_state(args.state)
    plan = load_plan(state["plan"])
    if plan.sha256 != state["plan_sha256"]:
        raise PlanError(f"{state['plan']} changed since the plan started; resume needs the same "
                        "plan file")  # fmt: skip
    if plan.folder.resolve() != folder.resolve():
        raise PlanError(f"{folder}: the plan's sessions go to {plan.folder}, not here")
    done = sum(s["status"] == "done" for s in state["steps"])
    nxt = next((s["name"] for s in state["steps"] if s["status"] != "done"), None)
    if nxt is None:
        print(f"plan {state['name']}: all {len(state['steps'])} step(s) already done")
        return 0
    tripped = next((s for s in state["steps"] if s["status"] == "tripped"), None)
    if tripped is not None and not confirm_after_trip(tripped, args.yes):
        print(f"plan {state['name']}: not resumed (step {tripped['name']} stays tripped)",
              flush=True)  # fmt: skip
        return 3
    print(f"plan {state['name']}: {done} of {len(state['steps'])} step(s) done; resuming at "
          f"{nxt}", flush=True)  # fmt: skip
    return execute(plan, state, _devices(args), ask=asker(args.prompt),
                   assume_loaded=args.assume_loaded)  # fmt: skip


def confirm_after_trip(entry: dict[str, Any], yes: bool) -> bool:
    """Whether to continue a plan whose step ``entry`` ended on a safety trip: ``yes``
    (``--yes``), else the operator's answer on stdin; no operator (end of input) is a
    PlanError, one line naming ``--yes``."""
    why = entry.get("result", "a safety trip")
    if yes:
        print(f"step {entry['name']} ended on a safety trip ({why}); continuing (--yes)",
              flush=True)  # fmt: skip
        return True
    print(f"step {entry['name']} ended on a safety trip ({why}). Has the cause been found and "
          "fixed? Continue with this step? [y/N] ", end="", flush=True)
    line = sys.stdin.readline() if sys.stdin is not None else ""
    if not line:
        print(flush=True)
        raise PlanError(f"step {entry['name']} ended on a safety trip ({why}) and nobody is at "
                        "the terminal to confirm: resume with --yes once the cause is fixed")
    return line.strip().lower() in ("y", "yes")


def _device_args(s: argparse.ArgumentParser) -> None:
    from smabench import argtypes
    from smabench.bench.headless import add_device_options

    add_device_options(s, "run each step on the mock bench", argtypes.serial_port)
    s.add_argument("--assume-loaded", action="store_true",
                   help="do not stop for load changes (the operator is not needed)")  # fmt: skip
    s.add_argument("--prompt", choices=("auto", "gui", "terminal"), default="auto",
                   help="load-change prompt: a dialog (gui), the terminal, or the dialog when "
                   "a display is available (auto)")  # fmt: skip


def add_commands(sub) -> None:
    """Register ``plan run`` and ``plan resume``."""
    s = sub.add_parser("plan", help="campaigns: run a test plan (TOML) unattended, resume it")
    psub = s.add_subparsers(dest="plan_command", required=True, metavar="WHAT")
    r = psub.add_parser("run", help="run a plan (or --dry-run: durations, current, energy)")
    r.add_argument("plan", help="plan file (TOML), e.g. sessions/plans/example.toml")
    r.add_argument("--dry-run", action="store_true", help="check and print the budget only")
    _device_args(r)
    r.set_defaults(func=cmd_plan_run)
    r = psub.add_parser("resume", help="continue a plan at its first unfinished step")
    r.add_argument("state", help="the plan's folder or its plan-state.json")
    r.add_argument("--yes", action="store_true",
                   help="continue after a step's safety trip without asking (the cause fixed)")
    _device_args(r)
    r.set_defaults(func=cmd_plan_resume)
