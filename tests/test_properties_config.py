"""Property tests (Hypothesis) of the configuration files: plan TOML, sensor register maps and
run settings. Random valid inputs round-trip exactly; random invalid ones give one line and
exit 2 (or the module's one error type) and leave nothing behind."""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smabench.drivers.displacement import SensorMapError, available_maps, load_map
from smabench.plan import PlanError, load_plan
from smabench.settings import SETTINGS, SettingError, check_value, defaults

FAST = settings(max_examples=20, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
CLI = settings(FAST, max_examples=8)
EXAMPLE = Path(__file__).resolve().parents[1] / "sessions" / "plans" / "example.toml"
MAPS = Path(__file__).resolve().parents[1] / "drivers" / "sensors"


def _set_step_value(text: str, step: int, key: str, value: str) -> str:
    """``text`` with ``key = value`` in the ``step``-th [[step]] table (0-based)."""
    parts = text.split("[[step]]")
    body = parts[step + 1]
    line = re.compile(rf"^{re.escape(key)}\s*=.*$", re.M)
    body = line.sub(f"{key} = {value}", body) if line.search(body) else f"\n{key} = {value}" + body
    parts[step + 1] = body
    return "[[step]]".join(parts)


@given(order=st.permutations(range(5)), cycles=st.integers(min_value=1, max_value=5))
@FAST
def test_a_valid_plan_reads_back_as_written(tmp_path_factory, order, cycles):
    text = EXAMPLE.read_text()
    n_steps = text.count("[[step]]")
    head, *steps = text.split("[[step]]")
    order = [k for k in order if k < n_steps] + [k for k in range(5, n_steps)]
    shuffled = head + "".join("[[step]]" + steps[k] for k in order)
    shuffled = _set_step_value(shuffled, 0, "cycles", str(cycles))
    path = tmp_path_factory.mktemp("plan") / "p.toml"
    path.write_text(shuffled)
    plan = load_plan(path)
    doc = tomllib.loads(shuffled)
    assert [s["name"] for s in plan.steps] == [s["name"] for s in doc["step"]]
    assert plan.steps[0]["cycles"] == cycles
    for mine, written in zip(plan.steps, doc["step"], strict=True):
        assert {k: mine[k] for k in written} == written


@given(key=st.sampled_from(["cycles", "current_a", "load_kg", "heat_s", "protocol", "bogus_key"]),
       value=st.one_of(st.just('"x"'), st.just("-1"), st.just("1e9"), st.just("nan"),
                       st.just("[1, 2]"), st.just("true")))  # fmt: skip
@CLI
def test_a_wrong_plan_value_is_one_line_exit_2_and_nothing_written(
    tmp_path_factory, cli_in_process, key, value
):
    bad = _set_step_value(EXAMPLE.read_text(), 1, key, value)
    try:
        load_plan_text = tomllib.loads(bad)
    except tomllib.TOMLDecodeError:
        load_plan_text = None
    tmp = tmp_path_factory.mktemp("badplan")
    (tmp / "p.toml").write_text(bad.replace('out = "sessions/plans-out"', f'out = "{tmp}/out"'))
    try:
        load_plan(tmp / "p.toml")
        return  # a value that happens to be valid for this key (e.g. cycles = true is refused)
    except PlanError:
        pass
    assert load_plan_text is None or load_plan_text["step"][1].get(key) is not None
    proc = cli_in_process("plan", "run", tmp / "p.toml", "--dry-run")
    assert proc.returncode == 2, proc
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert sorted(p.name for p in tmp.iterdir()) == ["p.toml"]


@given(junk=st.binary(max_size=200))
@FAST
def test_junk_plan_file_is_a_plan_error(tmp_path_factory, junk):
    path = tmp_path_factory.mktemp("junk") / "p.toml"
    path.write_bytes(junk)
    try:
        load_plan(path)
    except PlanError as exc:
        assert "\n" not in str(exc).strip() or "TOML" in str(exc)
    else:  # pragma: no cover - junk is never a complete plan
        raise AssertionError("junk accepted as a plan")


@given(name=st.sampled_from(sorted(available_maps())))
@FAST
def test_shipped_sensor_maps_round_trip_through_their_file(tmp_path_factory, name):
    shipped = load_map(name)
    copy = tmp_path_factory.mktemp("map") / f"{name}.toml"
    copy.write_bytes((MAPS / f"{name}.toml").read_bytes())
    assert dataclasses.replace(load_map(copy), source=shipped.source) == shipped


@given(name=st.sampled_from(sorted(available_maps())),
       cut=st.integers(min_value=1, max_value=400))  # fmt: skip
@FAST
def test_a_cut_or_mangled_sensor_map_is_one_error(tmp_path_factory, name, cut):
    text = (MAPS / f"{name}.toml").read_text()
    lines = text.splitlines()
    k = cut % len(lines)
    mangled = "\n".join(lines[:k] + ["unit = = 3"] + lines[k + 1 :])
    path = tmp_path_factory.mktemp("badmap") / "m.toml"
    path.write_text(mangled)
    try:
        load_map(path)
    except SensorMapError as exc:
        assert str(exc)
    else:  # pragma: no cover
        raise AssertionError("a map with invalid TOML was accepted")


NUMERIC = sorted(k for k, s in SETTINGS.items() if s.kind in ("float", "int") and s.max is not None
                 and not isinstance(s.max, str))  # fmt: skip


@given(key=st.sampled_from(NUMERIC), frac=st.floats(min_value=0.0, max_value=1.0))
@FAST
def test_a_setting_in_range_reads_back_exactly(key, frac):
    s = SETTINGS[key]
    lo = s.min if s.min is not None else 0.0
    hi = float(s.max)
    v = lo + frac * (hi - lo)
    if s.kind == "int":
        v = int(round(v))
    if (s.min_open and v <= lo) or (s.max_open and v >= hi) or not lo <= v <= hi:
        return
    assert check_value(key, v) == v
    assert check_value(key, str(v)) == v  # as typed on a command line or in a file


@given(key=st.sampled_from(NUMERIC),
       bad=st.sampled_from([math.nan, math.inf, -math.inf, 1e30, -1e30, "abc", ""]))  # fmt: skip
@FAST
def test_a_setting_out_of_range_is_one_line(key, bad):
    if bad == "" and SETTINGS[key].optional:
        return  # an empty optional setting means "none" (its none_text)
    try:
        check_value(key, bad)
    except SettingError as exc:
        assert str(exc) and "\n" not in str(exc)
    else:
        raise AssertionError(f"{key} accepted {bad!r}")


def test_defaults_are_valid_settings():
    for key, value in defaults().items():
        if value is not None:
            assert check_value(key, value) == value, key
