"""The E-STOP key on a real X server: input to command ≤ 20 ms with the Live plots drawing
(issue 25, point 4). The offscreen platform the other GUI tests use stamps no input event, so
there the banner's figure starts at the handler; on X11 (here Xvfb, a key injected through
XTEST) the event carries the server's time and the record starts at the press itself.
The case runs in its own pytest process (tests/xserver_estop_case.py) on a private Xvfb."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.realtime_bench]
HERE = Path(__file__).resolve().parent
INPUT_TO_COMMAND_LIMIT_MS = 20.0


@pytest.fixture
def xvfb():
    """A private Xvfb; yields its DISPLAY."""
    if not shutil.which("Xvfb"):
        if os.environ.get("CI"):
            pytest.fail("Xvfb missing under CI (make installs xvfb)")
        pytest.skip("Xvfb not installed")
    r, w = os.pipe()
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(w), "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
        pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()  # written once the server accepts connections
    try:
        assert number.isdigit(), proc.stderr.read().decode() if proc.poll() is not None else ""
        yield f":{number}"
    finally:
        proc.terminate()
        proc.wait(10)


def test_estop_key_press_to_command_within_20_ms_with_plots_drawing(xvfb, tmp_path):
    out = tmp_path / "xserver.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    env.update(DISPLAY=xvfb, QT_QPA_PLATFORM="xcb", SMABENCH_XSERVER_OUT=str(out))
    env.pop("WAYLAND_DISPLAY", None)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
         "-o", "addopts=", "--basetemp", str(tmp_path / "case"),
         str(HERE / "xserver_estop_case.py")],
        cwd=HERE.parent, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    m = json.loads(out.read_text())
    print(json.dumps(m))
    assert m["source"] == "key Esc" and m["from_input_event"] is True, m
    # the press's own time (X server milliseconds), not the handler's; Xvfb (a process at
    # normal priority, here beside the test's load) stamps it when it takes the XTEST request
    assert -2.0 <= m["input_after_press_ms"] <= 50.0, m
    assert 0.0 <= m["input_to_command_ms"] <= INPUT_TO_COMMAND_LIMIT_MS, m
    assert m["acked"] is True and m["input_to_below_20ma_ms"] < 1000.0, m
