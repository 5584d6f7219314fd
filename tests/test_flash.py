"""From a blank Arduino to a session: the real bootloaders in simavr, avrdude, the auto-reset.

The emulated Nano (``smabench-sim --bootloader HEX``) runs optiboot built from Debian's source
(``make -C firmware optiboot``) or Debian's old Nano bootloader, and every open of its pty resets
it into the bootloader as the DTR pulse does. avrdude's STK500v1 talks to the bootloader's own
code; what the tests check is measured on the device side: the resets and their causes (the
harness's ``AVR reset at t=… ms (MCUSR=…)`` lines, AVR time), and what the flashed firmware
answers over the protocol.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from smabench.drivers.current_source import CurrentSource, LinkTimeout
from smabench.drivers.mock.bench import BOOTLOADER_HEX, SIM_BIN, SIM_ELF, realtime_child

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

REPO = Path(__file__).resolve().parent.parent
APP_HEX = SIM_ELF.with_suffix(".hex")  # `make -C firmware elf` writes both
OLD_NANO_HEX = Path(
    "/usr/share/arduino/hardware/arduino/avr/bootloaders/atmega/ATmegaBOOT_168_atmega328.hex"
)
EXTRF, WDRF = 0x02, 0x08

_MISSING = [str(p) for p in (SIM_BIN, SIM_ELF, APP_HEX, BOOTLOADER_HEX) if not p.is_file()]
if shutil.which("avrdude") is None:
    _MISSING.append("avrdude (apt-get install avrdude)")
# under CI a missing build is a failure, never a skip
requires_emulator = pytest.mark.skipif(
    bool(_MISSING) and not os.environ.get("CI"),
    reason=f"missing: {_MISSING} (make -C firmware elf sim; apt-get install avrdude "
    "arduino-core-avr)",
)
RESET = re.compile(r"AVR reset at t=([\d.]+) ms \(MCUSR=0x([0-9a-f]{2})")


class BootHarness:
    """smabench-sim with a bootloader; ``resets()`` lists (AVR time ms, MCUSR) from its stderr.
    Real-time where allowed, as the mock bench runs it (a Nano is not slowed by host load)."""

    def __init__(self, bootloader: Path, app: Path | None) -> None:
        self.proc = subprocess.Popen(
            [str(SIM_BIN), "--bootloader", str(bootloader), str(app) if app else "--blank"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
            preexec_fn=realtime_child,
        )
        first = self.proc.stdout.readline().strip()
        assert first.startswith("PTY "), first
        self.port = first[4:]
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read_err, daemon=True).start()

    def _read_err(self) -> None:
        for line in self.proc.stderr:
            self.lines.put(line.strip())

    def resets(self) -> list[tuple[float, int]]:
        while True:
            try:
                self.seen.append(self.lines.get_nowait())
            except queue.Empty:
                break
        return [(float(m[1]), int(m[2], 16)) for m in map(RESET.search, self.seen) if m]

    def wait_resets(self, n: int, timeout_s: float = 20.0) -> list[tuple[float, int]]:
        """The resets once there are ``n`` of them (or what there is after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while len(self.resets()) < n and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.resets()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()  # EOF ends the harness
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def harness_factory():
    made: list[BootHarness] = []

    def make(bootloader: Path = BOOTLOADER_HEX, app: Path | None = None) -> BootHarness:
        h = BootHarness(bootloader, app)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


# ------------------------------------------------------------------ the CLI without a board
def flash_cli(capsys, *args) -> tuple[int, str, str]:
    """``smabench firmware flash ARGS`` in this process: (exit code, stdout, stderr)."""
    from smabench.cli import main

    code = main(["firmware", "flash", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_missing_avrdude_is_one_line_and_exit_2(capsys, monkeypatch, tmp_path):
    port = tmp_path / "ttyFAKE"
    port.touch()
    monkeypatch.setenv("PATH", str(tmp_path))  # no avrdude on it
    code, _, err = flash_cli(capsys, "--port", port, "--hex", APP_HEX)
    assert code == 2
    assert err.strip().splitlines() == [
        "smabench firmware flash: avrdude not found: apt-get install avrdude"
    ]


def test_bad_port_and_bad_hex_are_refused_before_avrdude(capsys, monkeypatch, tmp_path):
    code, _, err = flash_cli(capsys, "--port", tmp_path / "nothing", "--hex", APP_HEX)
    assert code == 2 and "no such port" in err and len(err.strip().splitlines()) == 1
    fake = tmp_path / "bin"  # an avrdude that must never be reached
    fake.mkdir()
    (fake / "avrdude").write_text("#!/bin/sh\necho called >> \"$0.log\"\nexit 1\n")
    (fake / "avrdude").chmod(0o755)
    monkeypatch.setenv("PATH", str(fake))
    bad = tmp_path / "bad.hex"
    bad.write_text("this is not intel hex\n")
    port = tmp_path / "ttyFAKE"
    port.touch()
    code, _, err = flash_cli(capsys, "--port", port, "--hex", bad)
    assert code == 2 and "bad.hex:1: not an Intel hex record" in err
    assert not (fake / "avrdude.log").exists()


def test_no_bootloader_answering_is_one_line_naming_both_baud_rates(capsys, monkeypatch, tmp_path):
    fake = tmp_path / "bin"  # avrdude as on a port with no board: never in sync
    fake.mkdir()
    script = "#!/bin/sh\necho \"$@\" >> \"$0.log\"\n"
    script += "echo 'avrdude error: programmer is not responding' >&2\nexit 1\n"
    (fake / "avrdude").write_text(script)
    (fake / "avrdude").chmod(0o755)
    monkeypatch.setenv("PATH", str(fake))
    port = tmp_path / "ttyFAKE"
    port.touch()
    hex_path = tmp_path / "app.hex"
    hex_path.write_text(":020000000C945E\n:00000001FF\n")
    code, out, err = flash_cli(capsys, "--port", port, "--hex", hex_path)
    assert code == 1
    assert len(err.strip().splitlines()) == 1 and "no bootloader answered" in err
    calls = (fake / "avrdude.log").read_text().splitlines()
    assert [c.split(" -b ")[1].split()[0] for c in calls] == ["115200", "57600"]
    assert all(f"-U flash:w:{hex_path}:i" in c and "-c arduino" in c for c in calls)


# ------------------------------------------------------------------ the emulated Nano
@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.timeout(120)
@requires_emulator
def test_blank_nano_flashed_then_a_session_runs_on_it(cli, capsys, tmp_path):
    """Blank emulated Nano → smabench firmware flash → smabench run → rows in the CSV."""
    from smabench.bench.headless import MockProcess

    with MockProcess(["--firmware", "emulated", "--bootloader", "--blank"]) as mock:
        port = mock.ports.driver
        # blank: the bootloader runs, then the empty flash; nothing answers the protocol
        blank = CurrentSource(port)
        with pytest.raises(LinkTimeout):
            blank.connect()
        blank.close()

        code, stdout, stderr = flash_cli(capsys, "--port", port, "--hex", APP_HEX)
        assert code == 0, stderr
        assert "written and verified at 115200 baud" in stdout
        m = re.search(r"firmware: (\S+) (\d+\.\d+\.\d+) \(protocol (\d+)", stdout)
        assert m, stdout
        name, version = m[1], m[2]

        # smabench run in this process (no interpreter start); what it sets for its own process
        # is put back after: the SIGTERM handler, this thread's (real-time loop) scheduling
        sigterm = signal.getsignal(signal.SIGTERM)
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        try:
            out = cli(
                "run", "--port", port, "--sensor", mock.ports.sensor_tcp, "--load-kg", "2",
                "--cycles", "1", "--current-a", "1.0", "--heat-s", "1", "--cool-timeout-s", "1",
                "--out", tmp_path, "--session-id", "flashed", "--quiet",
            )  # fmt: skip
        finally:
            signal.signal(signal.SIGTERM, sigterm)
            os.sched_setscheduler(0, policy, param)
        assert out.returncode == 0, out.stderr
    folder = tmp_path / "flashed"
    meta = json.loads((folder / "session.json").read_text())
    driver = meta["devices"]["current_driver"]
    assert driver["name"] == name
    assert ".".join(map(str, driver["firmware_version"])) == version
    with open(folder / "samples.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) > 100  # 1 s heating + cooling at 200 Hz
    heating = [float(r["current_A"]) for r in rows if float(r["current_set_A"] or 0) > 0]
    assert heating and max(heating) > 0.9  # the flashed firmware drove the current it was set


@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.timeout(120)
@requires_emulator
def test_old_nano_bootloader_is_flashed_at_57600_after_115200_fails(capsys, harness_factory):
    if not OLD_NANO_HEX.is_file():
        pytest.skip("apt-get install arduino-core-avr")
    h = harness_factory(OLD_NANO_HEX)
    code, stdout, stderr = flash_cli(capsys, "--port", h.port, "--hex", APP_HEX)
    assert code == 0, stderr
    # tried first, and failed: the probe, not avrdude's 5 s serial timeout
    assert "115200 baud (optiboot): no answer to GET_SYNC" in stdout
    assert "written and verified at 57600 baud" in stdout
    assert "firmware: SMA-CD328" in stdout
    # four opens of the port (probes at 115200 and 57600, avrdude at 57600, identify), four
    # external resets on the device
    resets = h.wait_resets(4)
    assert [mcusr & EXTRF for _, mcusr in resets].count(EXTRF) >= 4


@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.timeout(60)
@requires_emulator
def test_connect_waits_through_the_auto_reset(harness_factory):
    """Each open resets the MCU into optiboot, which holds it ≈ 1.4 s (3 LED flashes, 1 s
    watchdog) unless spoken to; the driver's handshake gets through on every (re)connect."""
    h = harness_factory(BOOTLOADER_HEX, SIM_ELF)
    # power-on: optiboot starts the application at once (no EXTRF)
    assert h.resets() == []

    # an open with nothing sent: the bootloader waits, then its watchdog starts the application
    fd = os.open(h.port, os.O_RDWR | os.O_NOCTTY)
    try:
        resets = h.wait_resets(2)
    finally:
        os.close(fd)
    (t_ext, c_ext), (t_wdt, c_wdt) = resets[:2]
    assert c_ext & EXTRF and c_wdt & WDRF
    assert 1000.0 <= t_wdt - t_ext <= 2000.0  # AVR ms: optiboot's wait before the application

    for attempt in range(2):  # connect, then a second open: another reset, another handshake
        source = CurrentSource(h.port)
        try:
            info = source.connect()
        finally:
            source.close()
        assert info.name == "SMA-CD328"
        resets = h.wait_resets(4 + 2 * attempt)  # this open's external and watchdog resets
        external = [t for t, c in resets if c & EXTRF]
        assert len(external) == 2 + attempt, resets  # this open reset the board
        # the application answered only after the bootloader handed over (watchdog reset)
        assert any(c & WDRF and t > external[-1] for t, c in resets), resets


def test_a_failed_verify_is_reported_not_retried_at_another_baud(capsys, monkeypatch, tmp_path):
    fake = tmp_path / "bin"  # the bootloader answered, then the flash read back wrong
    fake.mkdir()
    script = "#!/bin/sh\necho \"$@\" >> \"$0.log\"\n"
    script += "echo 'avrdude: AVR device initialized and ready to accept instructions' >&2\n"
    script += "echo 'avrdude error: verification mismatch, first mismatch at byte 0x0000' >&2\n"
    (fake / "avrdude").write_text(script + "exit 1\n")
    (fake / "avrdude").chmod(0o755)
    monkeypatch.setenv("PATH", str(fake))
    port = tmp_path / "ttyFAKE"
    port.touch()
    hex_path = tmp_path / "app.hex"
    hex_path.write_text(":020000000C945E\n:00000001FF\n")
    code, _, err = flash_cli(capsys, "--port", port, "--hex", hex_path)
    assert code == 1 and "verification mismatch" in err and "115200" in err
    assert len((fake / "avrdude.log").read_text().splitlines()) == 1


def hex_extent(path: Path) -> tuple[int, int]:
    """[lowest, highest] byte address with data in an Intel hex file (no extended records)."""
    lo, hi = 1 << 20, -1
    for line in path.read_text().split():
        n, addr, kind = int(line[1:3], 16), int(line[3:7], 16), line[7:9]
        if kind == "00" and n:
            lo, hi = min(lo, addr), max(hi, addr + n - 1)
    return lo, hi


DEBIAN_OPTIBOOT = OLD_NANO_HEX.parents[1] / "optiboot" / "optiboot_atmega328.hex"


@pytest.mark.emulator
@pytest.mark.slow  # starts the emulator
@requires_emulator
def test_debians_optiboot_overflows_the_chip_and_ours_fits():
    """Debian rebuilds optiboot with its avr-gcc: 532 B from 0x7E00, past the 32 KB flash. The
    emulator refuses it as avrdude would; `make -C firmware optiboot` builds the same source to
    fit the 512 B boot section, with the version word at 0x7FFE."""
    if not DEBIAN_OPTIBOOT.is_file():
        pytest.skip("apt-get install arduino-core-avr")
    lo, hi = hex_extent(DEBIAN_OPTIBOOT)
    assert lo == 0x7E00 and hi > 0x7FFF  # the package's image as shipped
    proc = subprocess.run(
        [str(SIM_BIN), "--bootloader", str(DEBIAN_OPTIBOOT), "--blank"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert proc.returncode == 2 and "no chip can hold this image" in proc.stderr
    lo, hi = hex_extent(BOOTLOADER_HEX)
    assert lo == 0x7E00 and hi == 0x7FFF


def test_an_avrdude_that_hangs_is_run_once_more(capsys, monkeypatch, tmp_path):
    """avrdude hung once after "AVR device initialized" on the emulated Nano under load: after
    AVRDUDE_TIMEOUT_S it is run again (the whole image written again), at the same baud rate."""
    from smabench import firmware_cli

    fake = tmp_path / "bin"  # hangs on its first call, succeeds on the second
    fake.mkdir()
    wc, sleep = shutil.which("wc"), shutil.which("sleep")  # PATH holds only the fake below
    script = "#!/bin/sh\necho \"$@\" >> \"$0.log\"\n"
    script += f"if [ $({wc} -l < \"$0.log\") -eq 1 ]; then exec {sleep} 30; fi\n"
    script += "echo 'avrdude: 26 bytes of flash verified' >&2\nexit 0\n"
    (fake / "avrdude").write_text(script)
    (fake / "avrdude").chmod(0o755)
    monkeypatch.setenv("PATH", str(fake))
    monkeypatch.setattr(firmware_cli, "AVRDUDE_TIMEOUT_S", 0.5)
    port = tmp_path / "ttyFAKE"  # not a serial port: no probe, avrdude at every baud rate
    port.touch()
    hex_path = tmp_path / "app.hex"
    hex_path.write_text(":020000000C945E\n:00000001FF\n")
    assert firmware_cli.flash(str(port), hex_path) == 115200
    calls = (fake / "avrdude.log").read_text().splitlines()
    assert len(calls) == 2 and all(" -b 115200 " in c for c in calls)
    assert "no result in 0.5 s; running it again" in capsys.readouterr().out
