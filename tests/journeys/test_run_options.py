"""Journey: a lab engineer mistypes an option of ``smabench run`` (and its siblings).

Every option error is one line on stderr and exit code 2, said before any device is opened: no
mock started, no port opened, no session folder written, within seconds. A mock that does not
become ready ends with one line within its readiness timeout. Library log lines (pymodbus's
"No response received …") stay off the console unless ``--verbose``.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from journeys.harness import Installed

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

QUICK_S = 20.0
"""An option error is said at start-up: the interpreter and the CLI's imports only (a few
seconds on a loaded 2-core machine), never a device's timeout or a mock's start-up."""

RUN = ("run", "--mock", "--load-kg", "2", "--cycles", "1", "--mock-speed", "5")

BAD_RUN_OPTIONS = [
    (("--mock-seed", "-1"), "--mock-seed"),
    (("--mock-adapter-latency-ms", "nan"), "--mock-adapter-latency-ms"),
    (("--mock-adapter-latency-ms", "-3"), "--mock-adapter-latency-ms"),
    (("--sensor-timeout-s", "inf"), "--sensor-timeout-s"),
    (("--sensor-timeout-s", "0"), "--sensor-timeout-s"),
    (("--mock-speed", "inf"), "--mock-speed"),
    (("--mock-speed", "nan"), "--mock-speed"),
    (("--load-kg", "nan"), "--load-kg"),
    (("--heat-s", "inf"), "--heat-s"),
    (("--current-a", "-1"), "--current-a"),
    (("--cycles", "1.5"), "--cycles"),
    (("--sensor-map", "no-such-map"), "no-such-map"),
]


def _refused_quickly(installed: Installed, cwd: Path, *args: object) -> str:
    t0 = time.monotonic()
    line = installed.usage_error(*args, cwd=cwd, timeout_s=120)
    elapsed_s = time.monotonic() - t0
    assert elapsed_s < QUICK_S, f"refused after {elapsed_s:.1f} s: {line}"
    assert not (cwd / "sessions").exists(), "a session folder was written for a refused option"
    return line


@pytest.mark.parametrize(("option", "named"), BAD_RUN_OPTIONS, ids=lambda x: " ".join(x)
                         if isinstance(x, tuple) else None)  # fmt: skip
def test_run_bad_option_is_one_line_before_the_mock(
    installed: Installed, cwd: Path, option: tuple[str, str], named: str
) -> None:
    args = list(RUN)
    if option[0] in args:  # the option replaces RUN's own value
        i = args.index(option[0])
        del args[i:i + 2]
    line = _refused_quickly(installed, cwd, *args, *option)
    assert named in line, line
    assert "time_t" not in line and "Traceback" not in line


def test_run_sensor_typo_is_named_before_the_port_is_opened(installed: Installed, cwd: Path):
    # the port exists (a character device) but is never opened: the sensor's typo is said first
    line = _refused_quickly(installed, cwd, "run", "--port", "/dev/null", "--sensor",
                            "tpc:127.0.0.1:5020", "--load-kg", "2")  # fmt: skip
    assert "tpc" in line and "--sensor" in line, line


def test_run_missing_port_is_named(installed: Installed, cwd: Path) -> None:
    line = _refused_quickly(installed, cwd, "run", "--port", "/dev/ttyUSB-no-such-port",
                            "--sensor", "tcp:127.0.0.1:5020", "--load-kg", "2")  # fmt: skip
    assert "/dev/ttyUSB-no-such-port" in line and "--port" in line, line


@pytest.mark.parametrize(
    "args",
    [
        ("mock", "--seed", "-1"),
        ("mock", "--speed", "nan"),
        ("mock", "--adapter-latency-ms", "inf"),
        ("mock", "--tcp-port", "70000"),
        ("simulate", "--out", "s", "--noise-mm", "nan"),
        ("simulate", "--out", "s", "--seed", "-1"),
        ("simulate", "--out", "s", "--heat-s", "inf"),
        ("demo", "--speed", "inf"),
        ("demo", "--load-kg", "nan"),
        ("demo", "--current-a", "nan"),
        ("sensor", "read", "--sensor", "tpc:127.0.0.1:5020"),
        ("sensor", "tare", "--sensor", "tcp:127.0.0.1:5020", "--duration-s", "inf"),
        ("calibrate", "wire", "--port", "/dev/null", "--wire-length-mm", "nan",
         "--wire-diameter-mm", "0.38"),
        ("calibrate", "current", "--port", "/dev/ttyUSB-no-such-port"),
        ("firmware", "flash", "--port", "/dev/ttyUSB-no-such-port"),
        ("plan", "run", "plan.toml", "--port", "/dev/null", "--sensor", "tpc:1.2.3.4:502"),
    ],
    ids=" ".join,
)
def test_other_commands_bad_option_is_one_line(installed: Installed, cwd: Path, args) -> None:
    if args[0] == "plan":
        (cwd / "plan.toml").write_text(
            '[plan]\nname = "p"\n[[step]]\nname = "a"\nprotocol = "cycles"\nload_kg = 1.0\n'
        )
    _refused_quickly(installed, cwd, *args)
    assert not (cwd / "s").exists()


def test_mock_that_is_not_ready_ends_with_one_line(installed: Installed, cwd: Path) -> None:
    # a readiness timeout no interpreter can meet: the mock is not ready in time
    t0 = time.monotonic()
    proc = installed.run(*RUN, "--quiet", cwd=cwd, timeout_s=120,
                         env={"SMABENCH_MOCK_READY_TIMEOUT_S": "0.2"})  # fmt: skip
    elapsed_s = time.monotonic() - t0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "ready" in lines[0] and "0.2 s" in lines[0], lines[0]
    assert elapsed_s < QUICK_S, f"{elapsed_s:.1f} s"


def test_a_bad_readiness_timeout_is_refused(installed: Installed, cwd: Path) -> None:
    line = installed.usage_error(*RUN, cwd=cwd, timeout_s=120,
                                 env={"SMABENCH_MOCK_READY_TIMEOUT_S": "nan"})  # fmt: skip
    assert "SMABENCH_MOCK_READY_TIMEOUT_S" in line, line


def test_library_log_lines_stay_off_the_console(installed: Installed, cwd: Path) -> None:
    # every sensor answer comes 80 ms late against a 20 ms request timeout: pymodbus logs "No
    # response received" for each; the user sees one line saying why the session ended
    proc = installed.run(*RUN, "--quiet", "--mock-adapter-latency-ms", "80",
                         "--sensor-timeout-s", "0.02", cwd=cwd, timeout_s=300)  # fmt: skip
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-3000:])
    assert len(lines) == 1, proc.stderr[-3000:]
    assert "sensor" in lines[0] and "No response" not in proc.stderr, lines
