"""The one settings schema: every range enforced, the front ends derived from it and consistent,
limits at the bench (high stress, position limits) and what reaches session.json."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import subprocess
from pathlib import Path

import pytest

from smabench import settings as S  # noqa: N812
from smabench.bench.remote import settings_from_json
from smabench.bench.session_run import RunSettings, session_meta
from smabench.cli import build_parser
from smabench.cli import main as cli_main
from smabench.control import MODES, ControllerSettings, PIDGains, gains_for_load
from smabench.physics.wire import PRESETS, Wire, stress_mpa
from smabench.protocols import ProtocolSettings

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

REPO = Path(__file__).resolve().parent.parent
NUMERIC = [s for s in S.SETTINGS.values() if s.kind in ("float", "int", "floats")]
# `smabench run` options before the schema (README, tests, scripts use them): all must stay
OLD_RUN_OPTIONS = str.split(
    "--load-kg --protocol --cycles --current-a --heat-s --cool-timeout-s --partial-cool-s "
    "--inner-heat-s --inner-cool-s --controller --switch-at --amplitude-mm --offset-mm "
    "--period-s --lead-in-s --kp --ki --kd --ffpid-gains --ffpid-hold-gains --ff-model "
    "--no-adapt --cooling-limit --rate-hz --wire --current-limit-a --temperature-limit-c "
    "--max-duration-s --out --session-id --quiet --mock --port --sensor --mock-speed"
)


def run_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["run"]


def option_strings() -> set[str]:
    return {o for a in run_parser()._actions for o in a.option_strings}


def cli_settings(*argv: str) -> RunSettings:
    from smabench.bench.headless import settings_from_args

    args = build_parser().parse_args(["run", "--port", "/nonexistent", "--sensor", "tcp:x:1",
                                      *argv])  # fmt: skip
    return settings_from_args(args)


def outside(s: S.Setting) -> list[float]:
    """Values just outside the setting's range (an open end itself is outside)."""
    out = []
    q = 10.0**-s.decimals
    if s.min is not None:
        out.append(s.min if s.min_open else s.min - q)
    hi = s.max_value
    if hi is not None:
        out.append(hi if s.max_open else hi + q)
    return out


def inside(s: S.Setting) -> list[float]:
    lo, hi = s.widget_range()
    return [v for v in (lo, hi) if abs(v) < 1e8]


# --------------------------------------------------------------------------- the table itself
def test_every_setting_is_declared_completely():
    assert set(S.GROUPS) == {"load_wire", "protocol", "controller", "gains", "limits", "loop",
                             "session"}  # fmt: skip
    for s in S.SETTINGS.values():
        assert s.group in S.GROUPS and s.label and s.help.endswith((".", ")")), s.key
        assert s.kind in ("float", "int", "bool", "choice", "floats", "switches", "text")
        if s.kind in ("float", "int", "floats"):
            assert s.unit or s.kind == "int" or s.key == "time_scale", s.key
            assert s.min is not None and s.max is not None, s.key
        if s.kind == "choice":
            assert s.choices, s.key
        # the default is a valid value of its own setting
        assert s.check(s.default) == s.default, s.key
        if s.group == "protocol" and s.key != "protocol.name":
            assert s.protocols or s.references, s.key
    # the list: load, wire and its long-life stress, protocol, controller, every gain
    # set with the table as default, every limit, loop rate and time scale
    for key in ("load_kg", "wire_preset", "long_life_stress_mpa", "protocol.name",
                "controller.mode", "current_limit_a", "temperature_limit_c", "position_min_mm",
                "position_max_mm", "max_load_kg", "max_duration_s", "rate_hz", "time_scale"):
        assert key in S.SETTINGS  # fmt: skip
    for law, gs in S.GAIN_SETS.items():
        for key in gs.keys:
            s = S.SETTINGS[key]
            assert s.group == "gains" and s.default is None and s.none_text == "per-load table"
        assert [S.SETTINGS[k].live for k in gs.keys] == [True, True, True, False], law


@pytest.mark.parametrize("s", NUMERIC, ids=lambda s: s.key)
def test_every_range_is_enforced_with_a_message_naming_setting_value_and_range(s):
    for v in inside(s):
        value = (v,) if s.kind == "floats" else v
        got = S.check_value(s.key, value)
        if s.kind == "floats":
            got, value = list(got), list(value)
        assert got == pytest.approx(value), (s.key, value, got)  # accepted, and kept as given
    for v in [*outside(s), math.nan, math.inf]:
        value = (v,) if s.kind == "floats" else v
        with pytest.raises(S.SettingError) as err:
            S.check_value(s.key, value)
        msg = str(err.value)
        assert s.label in msg and s.key in msg and len(msg.splitlines()) == 1, msg
        if math.isfinite(v):
            assert s.range_text.split(",")[0] in msg and f"got {v:g}" in msg, msg
    with pytest.raises(S.SettingError, match="must be a number"):
        S.check_value(s.key, ("abc",) if s.kind == "floats" else "abc")
    if s.kind == "int":
        with pytest.raises(S.SettingError, match="whole number"):
            S.check_value(s.key, s.min + 0.5)
    if not s.optional:
        with pytest.raises(S.SettingError):
            S.check_value(s.key, None)


def test_choices_bools_and_switches():
    with pytest.raises(S.SettingError, match="unknown controller 'bang'; choose from open_loop"):
        S.check_value("controller.mode", "bang")
    assert S.check_value("controller.mode", None) is None  # no controller
    with pytest.raises(S.SettingError, match="unknown wire 'steel'"):
        S.check_value("wire_preset", "steel")
    assert S.check_value("allow_high_stress", "yes") is True
    with pytest.raises(S.SettingError, match="true or false"):
        S.check_value("allow_high_stress", 1.5)
    assert S.check_value("controller.switches", ["3:ff", (8, "pid")]) == ((3.0, "ff"),
                                                                         (8.0, "pid"))
    for bad in ("-1:ff", "3", "x:ff", "3:bang"):
        with pytest.raises(S.SettingError, match="law switch"):
            S.check_value("controller.switches", [bad])
    with pytest.raises(S.SettingError, match="plain folder name"):
        S.check_value("session_id", "../elsewhere")


def test_one_place_for_each_fact():
    """The dataclasses' defaults and the choices other modules use are the schema's."""
    import smabench.protocols as protocols

    assert S.CONTROLLER_MODES is MODES
    assert protocols.PROTOCOL_NAMES is S.PROTOCOL_NAMES
    assert protocols.REFERENCE_NAMES is S.REFERENCE_NAMES
    for f in dataclasses.fields(ProtocolSettings):
        assert f.default == S.default(f"protocol.{f.name}"), f.name
    c = ControllerSettings()
    for key, v in c.values().items():
        if key != "controller.mode":  # the dataclass builds FF+PID; the schema: no controller
            assert v == S.default(key), key
    r = RunSettings(load_kg=S.default("load_kg"))
    for key, v in r.values().items():
        assert v == S.default(key), key
    assert "MAX_LOAD_KG" not in (REPO / "smabench/bench/session_run.py").read_text()


# --------------------------------------------------------------------------- command line
def test_every_setting_has_its_option_and_every_old_option_still_works():
    opts = option_strings()
    for name in OLD_RUN_OPTIONS:
        assert name in opts, name
    for s in S.SETTINGS.values():
        for name in s.cli_names():
            assert name in opts, (s.key, name)
    # the README's command table names only options that exist
    readme = (REPO / "README.md").read_text()
    rows = [ln for ln in readme.splitlines() if ln.startswith("| `smabench run")]
    assert rows
    for ln in rows:
        for name in re.findall(r"(--[a-z][a-z0-9-]+)", ln.split("` |")[0]):
            assert name in opts, name


def test_help_gives_unit_range_and_default(capsys):
    with pytest.raises(SystemExit) as done:
        cli_main(["run", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--heat-s S Heating time per cycle [(0, 600] s; default 3 s; for cycles" in text
    assert "--load-kg KG required: Hanging mass" in text and "(0, 10] kg" in text
    assert "--ffpid-hold-gains KP KI KD FF+PID hold gains: mm/mm, 1/s, s" in text
    assert "--position-min-mm MM" in text and "default no limit" in text
    assert "--allow-high-stress" in text


@pytest.mark.parametrize("s", [s for s in NUMERIC if s.cli_names()], ids=lambda s: s.key)
def test_out_of_range_option_is_refused_naming_option_and_range(s):
    opt = s.cli_names()[0]
    for v in outside(s):
        argv = ["--load-kg", "1", opt, repr(v)]
        if s.key == "load_kg":
            argv = argv[2:]
        with pytest.raises(ValueError) as err:
            cli_settings(*argv)
        msg = str(err.value)
        assert msg.endswith(f"({opt})") and s.range_text.split(",")[0] in msg, msg


@pytest.mark.parametrize("law", list(S.GAIN_SETS))
def test_gain_options_are_checked_in_their_units(law):
    gs = S.GAIN_SETS[law]
    opt = gs.cli_triple
    argv = [opt, "0.1", "-1", "0"] if opt else ["--kp", "0.1", "--ki", "-1"]
    with pytest.raises(ValueError) as err:
        cli_settings("--load-kg", "2", "--protocol", "sine", "--controller", "ffpid", *argv)
    assert f"{gs.label} gain ki must be in 0 … 100 {gs.units[1]}, got -1" in str(err.value)


CASES = [
    ([], {}),
    (["--protocol", "inner", "--cycles", "7", "--inner-heat-s", "0.3", "--current-limit-a",
      "1.8", "--position-min-mm", "-2", "--position-max-mm", "40", "--max-load-kg", "5"],
     {"protocol": {"name": "inner", "cycles": 7, "inner_heat_s": 0.3}, "current_limit_a": 1.8,
      "position_min_mm": -2, "position_max_mm": 40, "max_load_kg": 5}),
    (["--protocol", "step", "--levels-a", "0.2,0.6", "1.0", "--hold-s", "2", "--wire",
      "flexinol-0.38-70c"],
     {"protocol": {"name": "step", "levels_a": [0.2, 0.6, 1.0], "hold_s": 2},
      "wire_preset": "flexinol-0.38-70c"}),
    (["--protocol", "sine", "--controller", "ffpid", "--ffpid-gains", "0.2", "1.5", "0",
      "--ffpid-d-filter-s", "0.08", "--kp", "3", "--switch-at", "5:pid", "--no-observer",
      "--ff-model", "1", "--offset-mm", "3.9", "--rate-hz", "400"],
     {"protocol": {"name": "sine", "offset_mm": 3.9}, "rate_hz": 400,
      "controller": {"mode": "ffpid", "ffpid_gains": [0.2, 1.5, 0, 0.08], "gains": {"kp": 3},
                     "switches": [[5, "pid"]], "observer": False, "model": "1"}}),
]  # fmt: skip


@pytest.mark.parametrize(("argv", "cfg"), CASES)
def test_command_line_and_json_give_the_same_settings(argv, cfg, monkeypatch):
    # building the closed-loop controller identifies the loop model (slow): not needed here
    monkeypatch.setattr(RunSettings, "build_controller", lambda self: None)
    a = cli_settings("--load-kg", "1.5", *argv)
    b = settings_from_json({"load_kg": 1.5, "out_dir": "sessions", **cfg})
    assert a.values() == b.values()
    assert a == b
    # and the JSON the session records reads back to the same settings
    c = settings_from_json(json.loads(json.dumps(session_meta(a, {})["settings"])))
    assert c.values() == a.values()


def test_gains_left_out_come_from_the_per_load_table(monkeypatch):
    monkeypatch.setattr(RunSettings, "build_controller", lambda self: None)
    s = cli_settings("--load-kg", "2", "--protocol", "sine", "--controller", "pid", "--kp", "4")
    table = gains_for_load(2.0)
    assert s.controller.gains == PIDGains(4.0, table.ki, table.kd, table.d_filter_s)
    assert s.controller.ffpid_gains is None and s.controller.ffpid_hold_gains is None
    s = cli_settings("--load-kg", "2", "--protocol", "sine", "--controller", "ffpid",
                     "--ffpid-hold-gains", "0", "0.05", "0")  # fmt: skip
    tf = gains_for_load(2.0, law="ffpid_hold").d_filter_s
    assert s.controller.ffpid_hold_gains == PIDGains(0.0, 0.05, 0.0, tf)


def test_json_refuses_unknown_keys_and_malformed_gains():
    with pytest.raises(ValueError, match="unknown setting load_lb"):
        settings_from_json({"load_kg": 1, "load_lb": 2})
    with pytest.raises(ValueError, match="unknown setting protocol.heat_time"):
        settings_from_json({"load_kg": 1, "protocol": {"heat_time": 2}})
    with pytest.raises(ValueError, match=r"PID gains must be \[kp, ki, kd\]"):
        settings_from_json({"load_kg": 1, "protocol": {"name": "sine"},
                            "controller": {"mode": "pid", "gains": "fast"}})  # fmt: skip
    with pytest.raises(ValueError, match="load must be given"):
        settings_from_json({"protocol": {"name": "cycles"}})
    with pytest.raises(ValueError, match=r"heat time must be in \(0, 600\] s, got -1 s"):
        settings_from_json({"load_kg": 1, "protocol": {"heat_s": -1}})


@pytest.mark.parametrize("s", NUMERIC, ids=lambda s: s.key)
def test_json_enforces_the_same_ranges(s):
    for v in outside(s):
        value = [v] if s.kind == "floats" else v
        flat = {s.key: value}
        if s.group == "gains":  # gain components travel as their set
            gs = next(g for g in S.GAIN_SETS.values() if s.key.startswith(g.key + "."))
            flat = {k: (value if k == s.key else None) for k in gs.keys}
        cfg = S.to_mapping({"load_kg": 1.0, **flat})
        if "controller" in cfg:
            cfg["controller"]["mode"] = "pid"
        with pytest.raises(S.SettingError) as err:
            S.values_from_mapping(cfg)
        assert err.value.key == s.key and s.range_text.split(",")[0] in str(err.value)


# --------------------------------------------------------------------------- cross-setting rules
def test_rules_across_settings():
    with pytest.raises(ValueError, match=r"load 6 kg is above the max load 5 kg \(--load-kg\)"):
        cli_settings("--load-kg", "6", "--max-load-kg", "5", "--allow-high-stress")
    with pytest.raises(ValueError, match="position max 1 mm must be above position min 5 mm"):
        cli_settings("--load-kg", "1", "--position-min-mm", "5", "--position-max-mm", "1")
    with pytest.raises(ValueError, match=r"current 1.6 A is outside 0 … 1.5 A, the current lim"):
        cli_settings("--load-kg", "1", "--current-a", "1.6", "--current-limit-a", "1.5")
    with pytest.raises(ValueError, match=r"current levels 2.2 A is outside 0 … 2 A, the wire's"):
        cli_settings("--load-kg", "1", "--protocol", "step", "--levels-a", "1", "2.2",
                     "--current-limit-a", "2.4")  # fmt: skip
    s = cli_settings("--load-kg", "1", "--current-a", "1.9")
    with pytest.raises(ValueError, match=r"outside 0 … 1.8 A, the driver's limit"):
        s.validate(device_limit_a=1.8)
    with pytest.raises(ValueError, match="it needs a controller"):
        cli_settings("--load-kg", "1", "--protocol", "triangle")
    with pytest.raises(S.SettingError, match=r"current limit must be in \(0, 1.25\] A \(1.25 ×"):
        S.check_current_limit(1.5, Wire(max_current_a=1.0))
    # an open-ended bound keeps a spin box inside it at its decimals
    assert S.get("load_kg").widget_range() == (0.01, 10.0)


# --------------------------------------------------------------------------- high stress
def test_stress_check_against_the_wires_long_life_stress():
    wire = PRESETS["paper"]
    assert wire.long_life_stress_mpa == 172.0
    assert S.stress_check(2.0).needs_confirmation is False  # 172.9 MPa: at the figure
    for load, mpa in ((2.05, 177), (3.0, 259), (4.0, 346)):
        sc = S.stress_check(load)
        assert sc.needs_confirmation and round(sc.stress_mpa) == mpa
        assert sc.limit_mpa == 172.0 and sc.limit_load_kg == pytest.approx(1.989, abs=1e-3)
        assert f"{mpa} MPa" in sc.message and "172 MPa" in sc.message and "--" not in sc.message
    assert sc.stress_mpa == pytest.approx(stress_mpa(4.0, wire))
    assert S.stress_check(3.0, long_life_stress_mpa=300.0).needs_confirmation is False


def _assert_one_line_exit_2(proc, *needles):
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.mark.slow  # a `smabench run` subprocess: the path a user meets (in process: below)
def test_high_stress_needs_the_flag_on_the_command_line(run_cli, tmp_path):
    proc = run_cli("run", "--port", "/nonexistent/tty", "--sensor", "tcp:127.0.0.1:1",
                   "--load-kg", "3", "--out", tmp_path)  # fmt: skip
    _assert_one_line_exit_2(proc, "259 MPa", "long-life stress of 172 MPa",
                            "--allow-high-stress")  # fmt: skip
    assert not any(tmp_path.iterdir())
    s = cli_settings("--load-kg", "3", "--allow-high-stress")
    limits = session_meta(s, {})["limits"]
    assert limits["allow_high_stress"] is True and limits["above_long_life_stress"] is True
    assert limits["stress_MPa"] == pytest.approx(259.4, abs=0.05)
    with pytest.raises(ValueError, match="to run it anyway, give allow_high_stress"):
        settings_from_json({"load_kg": 3})


@pytest.mark.parametrize(
    ("argv", "needles"),
    [
        (["--load-kg", "12"], ["load must be in (0, 10] kg", "got 12 kg", "(--load-kg)"]),
        (["--load-kg", "2", "--heat-s", "0"], ["heat time must be in (0, 600] s", "--heat-s"]),
        (["--load-kg", "2", "--cycles", "0"], ["cycles must be in 1 … 10000, got 0"]),
        (["--load-kg", "2", "--temperature-limit-c", "300"], ["40 … 250 °C", "got 300 °C"]),
        (["--load-kg", "2", "--current-limit-a", "3"], ["current limit must be in (0, 2.5] A"]),
        (["--load-kg", "abc"], ["load must be a number, got 'abc' (--load-kg)"]),
        ([], ["load must be given: --load-kg KG"]),
    ],
)
def test_out_of_range_on_the_command_line_is_one_line_and_exit_2(capsys, tmp_path, argv,
                                                                  needles):  # fmt: skip
    """In process through the CLI's main (the subprocess path is the high-stress test's)."""
    code = cli_main(["run", "--port", "/nonexistent/tty", "--sensor", "tcp:127.0.0.1:1",
                     "--out", str(tmp_path), *argv])  # fmt: skip
    err = capsys.readouterr().err
    _assert_one_line_exit_2(subprocess.CompletedProcess([], code, "", err), *needles)
    assert not any(tmp_path.iterdir())


def test_limits_reach_the_runtime_and_session_meta():
    s = cli_settings("--load-kg", "1", "--position-min-mm", "-2", "--position-max-mm", "40",
                     "--current-limit-a", "1.5", "--temperature-limit-c", "140",
                     "--max-duration-s", "600", "--max-load-kg", "4")  # fmt: skip
    cfg = s.runtime_config()
    assert (cfg.position_min_mm, cfg.position_max_mm, cfg.current_limit_a) == (-2, 40, 1.5)
    assert (cfg.temperature_limit_c, cfg.max_duration_s) == (140, 600)
    limits = session_meta(s, {})["limits"]
    assert {k: limits[k] for k in ("position_min_mm", "position_max_mm", "max_load_kg")} == {
        "position_min_mm": -2.0, "position_max_mm": 40.0, "max_load_kg": 4.0}
    assert limits["above_long_life_stress"] is False and limits["allow_high_stress"] is False
    assert limits["stress_MPa"] == pytest.approx(86.5, abs=0.05)


@pytest.mark.slow
def test_limits_and_high_stress_reach_session_json(run_cli, tmp_path):
    """A short session on the mock: every limit and the allowed high stress are recorded."""
    proc = run_cli(
        "run", "--mock", "--mock-speed", "10", "--load-kg", "3", "--allow-high-stress",
        "--cycles", "1", "--current-a", "1.4", "--heat-s", "1", "--cool-timeout-s", "1",
        "--min-cool-s", "0.5", "--position-min-mm", "-20", "--position-max-mm", "60",
        "--max-load-kg", "5", "--current-limit-a", "1.8", "--temperature-limit-c", "150",
        "--out", tmp_path, "--session-id", "s", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "above the wire's long-life stress" in proc.stdout
    meta = json.loads((tmp_path / "s" / "session.json").read_text())
    assert meta["status"] == "completed"
    assert meta["limits"] == {
        "current_limit_a": 1.8, "temperature_limit_c": 150.0, "position_min_mm": -20.0,
        "position_max_mm": 60.0, "max_load_kg": 5.0, "max_duration_s": 3600.0,
        "stress_MPa": 259.4, "long_life_stress_MPa": 172.0, "above_long_life_stress": True,
        "allow_high_stress": True,
    }  # fmt: skip
    assert meta["settings"]["allow_high_stress"] is True
    assert meta["settings"]["protocol"]["min_cool_s"] == 0.5
    # no limit is null (valid JSON), not Infinity
    s = RunSettings(load_kg=1.0)
    text = json.dumps(session_meta(s, {}), allow_nan=False)
    assert json.loads(text)["limits"]["position_min_mm"] is None


# --------------------------------------------------------------------------- what the GUI uses
def test_fields_for_the_gui():
    inner = [s.key for s in S.fields("protocol", protocol="inner", closed_loop=False)]
    assert "protocol.inner_heat_s" in inner and "protocol.partial_cool_s" not in inner
    assert "protocol.amplitude_mm" not in inner
    sine = [s.key for s in S.fields("protocol", protocol="sine", closed_loop=True)]
    assert sine == ["protocol.name", "protocol.cycles", "protocol.amplitude_mm",
                    "protocol.offset_mm", "protocol.period_s", "protocol.lead_in_s",
                    "protocol.max_rise_mm_s"]  # fmt: skip
    step_open = [s.key for s in S.fields("protocol", protocol="step", closed_loop=False)]
    assert "protocol.levels_a" in step_open and "protocol.amplitude_mm" not in step_open
    for p in S.PROTOCOL_NAMES:
        assert len(S.fields("protocol", protocol=p)) >= 2
    ffpid = {s.key for s in S.fields("gains", mode="ffpid")}
    assert ffpid == {*S.GAIN_SETS["ffpid"].keys, *S.GAIN_SETS["ffpid_hold"].keys}
    assert {s.key for s in S.fields("gains", mode="pid")} == set(S.GAIN_SETS["pid"].keys)
    limits = [s.key for s in S.fields("limits")]
    assert limits == ["current_limit_a", "temperature_limit_c", "position_min_mm",
                      "position_max_mm", "max_load_kg", "max_duration_s"]  # fmt: skip
    kp = S.get("controller.ffpid_gains.kp")
    assert kp.tooltip.startswith("Proportional gain: FF+PID's gain while the setpoint moves")
    assert "Range: 0 … 100 mm/mm." in kp.tooltip and "per-load table" in kp.tooltip
    assert "Can change during a run." in kp.tooltip
    assert not S.get("load_kg").live and S.get("controller.mode").live
    assert S.error_for("current_limit_a", 0) == (
        "current limit must be in (0, 2.5] A, got 0 A (current_limit_a)")
    assert S.error_for("current_limit_a", 1.0) is None
    with pytest.raises(KeyError, match="no group"):
        S.fields("bogus")


@pytest.mark.parametrize(
    ("key", "text", "needle"),
    [
        ("mock.seed", "-1", "mock seed must be in 0 … 1e+09, got -1"),
        ("mock.seed", "1.5", "must be a whole number"),
        ("mock.adapter_latency_ms", "nan", "adapter latency must be in 0 … 1000 ms"),
        ("sensor_timeout_s", "inf", "sensor request timeout must be in 0.001 … 5 s"),
        ("mock.tcp_port", "70000", "0 … 65535"),
        ("mock.ready_timeout_s", "0", "(0, 3600] s"),
        ("time_scale", "inf", "time scale must be in 0.1 … 100"),
        ("load_kg", "nan", "load must be in (0, 10] kg"),
    ],
)
def test_device_options_refuse_out_of_range_and_non_finite(key, text, needle):
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(needle)):
        S.arg_type(key)(text)


def test_device_options_parse_in_their_type():
    assert S.arg_type("mock.seed")("7") == 7 and isinstance(S.arg_type("mock.seed")("7"), int)
    assert S.arg_type("sensor_timeout_s")("0.02") == pytest.approx(0.02)
    assert S.arg_type("mock.adapter_latency_ms")("16") == 16.0
    assert set(S.DEVICE_OPTIONS).isdisjoint(S.SETTINGS)  # not run settings: no GUI field, no JSON
