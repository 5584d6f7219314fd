"""Journey: a campaign (``smabench plan``) on the mock bench.

A step that trips a safety function (here the current driver's own energy budget, its
over-temperature trip) ends the plan, says why, and is never run again unattended; ``plan
resume`` asks before continuing and, with nobody at the terminal, refuses with one line. The dry
run predicts each step's peak wire temperature with the plant model and refuses a step above the
temperature limit or longer than ``max_step_s``. The README's campaign recipe runs as written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from journeys.harness import REPO, Installed

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

# 1.4 A held for 20 s: the driver's conservative energy budget (R at its hottest, the lowest
# convection) reaches its 180 °C maximum after ≈ 11 s and latches OVER-TEMPERATURE, while the
# plant model (and the host's estimate) stay below the plan's 240 °C limit: the dry run passes
# and the device trips the step, a safety trip that must not be retried.
HOT_PLAN = """
[plan]
name = "hot"
temperature_limit_c = 240
max_step_s = 600
out = "plans-out"
mock_speed = 5
retries = 2

[[step]]
name = "too-long-heat"
protocol = "cycles"
load_kg = 2.0
cycles = 1
current_a = 1.4
heat_s = 20.0
cool_timeout_s = 10.0
min_cool_s = 3.0

[[step]]
name = "after"
protocol = "cycles"
load_kg = 2.0
cycles = 1
current_a = 1.4
heat_s = 3.0
"""


@pytest.mark.slow
def test_a_safety_trip_ends_the_plan_and_is_not_retried(installed: Installed, cwd: Path):
    (cwd / "hot.toml").write_text(HOT_PLAN)
    proc = installed.run("plan", "run", "hot.toml", "--mock", "--assume-loaded", cwd=cwd,
                         timeout_s=300)  # fmt: skip
    assert proc.returncode == 1, (proc.returncode, proc.stdout[-3000:], proc.stderr[-3000:])
    assert "running the step again" not in proc.stdout, proc.stdout
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and "over-temperature" in err[0] and "plan resume" in err[0], err
    folder = cwd / "plans-out" / "hot"
    sessions = sorted(p.name for p in folder.iterdir() if p.is_dir())
    assert sessions == ["01-too-long-heat"], sessions  # one session: no retry, no second step
    state = json.loads((folder / "plan-state.json").read_text())
    assert state["steps"][0]["status"] == "tripped", state["steps"][0]
    assert "over-temperature" in state["steps"][0]["result"]
    assert state["steps"][1]["status"] == "pending"

    # nobody at the terminal: resume refuses with one line and runs nothing
    line = installed.usage_error("plan", "resume", folder, "--mock", cwd=cwd, timeout_s=120)
    assert "over-temperature" in line and "--yes" in line, line
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == sessions

    # the operator declines at the prompt: nothing runs either
    proc = installed.run("plan", "resume", folder, "--mock", cwd=cwd, input_text="no\n",
                         timeout_s=120)  # fmt: skip
    assert proc.returncode == 3, (proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == sessions


PEAK_PLAN = """
[plan]
name = "peak"
temperature_limit_c = {limit}
max_step_s = {max_step_s}

[[step]]
name = "mild"
protocol = "cycles"
load_kg = 2.0
cycles = 2
current_a = 1.0
heat_s = 2.0

[[step]]
name = "scorch"
protocol = "cycles"
load_kg = 2.0
cycles = 2
current_a = 1.8
heat_s = 12.0
"""


def test_dry_run_prints_each_steps_predicted_peak(installed: Installed, cwd: Path) -> None:
    (cwd / "p.toml").write_text(PEAK_PLAN.format(limit=250, max_step_s=3600))
    out = installed.ok("plan", "run", "p.toml", "--dry-run", cwd=cwd).stdout
    assert "peak °C" in out, out
    rows = {ln.split()[1]: ln for ln in out.splitlines() if ln.strip()[:1].isdigit()}
    assert set(rows) == {"mild", "scorch"}, out


def test_dry_run_refuses_a_step_whose_predicted_peak_exceeds_the_limit(
    installed: Installed, cwd: Path
) -> None:
    (cwd / "p.toml").write_text(PEAK_PLAN.format(limit=120, max_step_s=3600))
    line = installed.usage_error("plan", "run", "p.toml", "--dry-run", cwd=cwd)
    assert "scorch" in line and "120" in line and "°C" in line, line
    assert "mild" not in line


def test_dry_run_refuses_a_step_longer_than_max_step_s(installed: Installed, cwd: Path) -> None:
    (cwd / "p.toml").write_text(PEAK_PLAN.format(limit=250, max_step_s=30))
    line = installed.usage_error("plan", "run", "p.toml", "--dry-run", cwd=cwd)
    assert "max_step_s" in line and "30" in line, line


@pytest.mark.slow
def test_readme_campaign_recipe(installed: Installed, cwd: Path) -> None:
    """The README's commands, as written, from a clone's folder (the plan file is the clone's)."""
    plans = cwd / "sessions" / "plans"
    plans.mkdir(parents=True)
    shutil.copy(REPO / "sessions" / "plans" / "example.toml", plans / "example.toml")
    readme = (REPO / "README.md").read_text()
    assert "smabench plan run sessions/plans/example.toml --mock" in readme
    assert "smabench characterize sessions/plans-out/example/0*" in readme
    installed.ok("plan", "run", "sessions/plans/example.toml", "--dry-run", cwd=cwd)
    # the operator presses Enter at the load change (1 kg → 2 kg)
    installed.ok("plan", "run", "sessions/plans/example.toml", "--mock", cwd=cwd,
                 input_text="\n", timeout_s=600)  # fmt: skip
    sessions = sorted((cwd / "sessions" / "plans-out" / "example").glob("0*"))
    assert [p.name for p in sessions] == ["01-train-1kg", "02-cycles-2kg", "03-incomplete-2kg"]
    for s in sessions:
        assert json.loads((s / "session.json").read_text())["status"] == "completed", s
    installed.ok("characterize", *sessions, "--json", "out.json", "--report", "report/", cwd=cwd)
    doc = json.loads((cwd / "out.json").read_text())
    assert doc, doc
