"""The ``smabench`` command line: import, fit, simulate, demo, bench.

Every command has ``--help``. Bad input ends with one line on stderr and exit code 2, no traceback,
and nothing half-written.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

from smabench import __version__
from smabench.argtypes import OUTPUT_HELP, output_file, positive
from smabench.settings import add_setting_option

log = logging.getLogger("smabench")

EXIT_USAGE = 2

def default_data_dir() -> Path:
    """The measured Flexinol loops shipped as package data (``smabench.samples``)."""
    from smabench.samples import sample_dir

    return sample_dir("flexinol-isobaric")



class CliError(Exception):
    """An error to report as one line on stderr with exit code 2."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line on stderr (exit 2), pointing at ``--help``
    instead of printing the usage block (subparsers inherit the class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# Bad input, not a bug: our own error types (SessionError, TextImportError, FitError, effect
# errors) all derive from ValueError; OSError covers unreadable or unwritable paths.
USER_ERRORS: tuple[type[BaseException], ...] = (CliError, ValueError, OSError)


def _write_json_atomic(path: str | Path, obj: object) -> None:
    from smabench.sessions import atomic_write_json

    atomic_write_json(path, obj)


# --------------------------------------------------------------------------- import
def cmd_import(args: argparse.Namespace) -> int:
    from smabench.importer import import_text, preview

    if args.preview:
        print(preview(args.file, args.decimal))
        return 0
    if not args.columns or not args.out:
        raise CliError("import needs --columns and --out (or --preview to see the layout)")
    folder = import_text(
        args.file,
        args.columns,
        args.out,
        wire_length_mm=args.wire_length_mm,
        load_kg=args.load_kg,
        wire_diameter_mm=args.wire_diameter_mm,
        decimal=args.decimal,
        progress=_import_progress,
        write_progress=_import_write_progress,
    )
    from smabench.sessions import META_FILE

    done = json.loads((folder / META_FILE).read_text(encoding="utf-8"))["import"]
    empty = done["empty_cells"]
    kept = (f", {sum(empty.values())} empty cell(s) kept as NaN ("
            + ", ".join(f"{k} {v}" for k, v in empty.items()) + ")") if empty else ""  # fmt: skip
    print(f"{done['rows']} rows imported{kept}")
    print(f"session written: {folder}")
    return 0


def _import_progress(rows: int, bytes_read: int, bytes_total: int) -> None:
    print(f"import: {rows / 1e6:.2f} M rows, {bytes_read / 1e6:.0f} of {bytes_total / 1e6:.0f} MB",
          file=sys.stderr, flush=True)  # fmt: skip


def _import_write_progress(rows_done: int, rows: int) -> None:
    print(f"import: session {rows_done / 1e6:.2f} of {rows / 1e6:.2f} M rows written",
          file=sys.stderr, flush=True)  # fmt: skip


# --------------------------------------------------------------------------- simulate
def simulate_session(
    out: str | Path,
    load_kg: float,
    cycles: int,
    current_a: float,
    heat_s: float,
    cool_s: float,
    kind: str,
    effects: Sequence[str],
    rate_hz: float,
    noise_mm: float,
    seed: int,
    wire_name: str = "paper",
) -> Path:
    """Simulate heating cycles on the plant and write them as a session (contract columns)."""
    from smabench.physics.plant import Effects, heating_cycles_profile, simulate_plant
    from smabench.physics.thermal import simulate_temperature
    from smabench.physics.wire import PRESETS
    from smabench.sessions import write_session
    from smabench.settings import SettingError, check_value

    try:
        check_value("load_kg", load_kg)  # the run setting's range (smabench.settings)
    except SettingError as exc:
        raise CliError(exc.naming("--load-kg")) from None
    wire = PRESETS[wire_name]
    if not 0 < current_a <= wire.max_current_a:
        raise CliError(f"--current-a must be in (0, {wire.max_current_a}] A, got {current_a}")
    eff = Effects.from_strings(list(effects))
    dt_plant_s = 1e-3
    t_s, i_a = heating_cycles_profile(
        cycles, current_a, heat_s, cool_s, dt_plant_s, kind=kind, wire=wire, load_kg=load_kg,
        effects=eff,
    )  # fmt: skip
    trace = simulate_plant(
        t_s, i_a, load_kg=load_kg, wire=wire, effects=eff, noise_mm=noise_mm, seed=seed
    )
    step = max(1, int(round(1.0 / (rate_hz * dt_plant_s))))
    sel = slice(None, None, step)
    t_rec = trace.t_s[sel]
    i_rec = trace.current_a[sel]
    # What the bench would log as the temperature estimate: the heat balance driven by the
    # recorded current and a constant (not the effect-laden) ambient.
    temp_est = simulate_temperature(trace.t_s, trace.current_a, wire, 22.0, 22.0)[sel]
    period_s = heat_s + cool_s
    data = {
        "t_s": t_rec,
        "current_set_A": i_rec,
        "current_A": i_rec,
        "voltage_V": trace.voltage_v[sel],
        "ambient_C": np.full_like(t_rec, 22.0),
        "position_mm": trace.position_mm[sel],
        "temperature_est_C": temp_est,
        "mode": np.array(["open_loop"] * len(t_rec), dtype=object),
        "cycle": np.minimum(np.floor(t_rec / period_s), cycles - 1).astype(int),
        "flags": np.zeros(len(t_rec), dtype=int),
    }
    meta = {
        "kind": "simulated",
        "load_kg": load_kg,
        "wire": {"preset": wire_name, "length_mm": wire.length_mm, "diameter_mm": wire.diameter_mm},
        "protocol": {
            "name": f"cycles-{kind}",
            "cycles": cycles,
            "current_a": current_a,
            "heat_s": heat_s,
            "cool_s": cool_s,
        },
        "controller": {"mode": "open_loop"},
        "simulation": {
            "effects": list(effects),
            "noise_mm": noise_mm,
            "seed": seed,
            "rate_hz": rate_hz,
        },
        "status": "completed",
        "end_reason": "protocol completed",
    }
    return write_session(out, meta, data)


def cmd_simulate(args: argparse.Namespace) -> int:
    folder = simulate_session(
        args.out,
        args.load_kg,
        args.cycles,
        args.current_a,
        args.heat_s,
        args.cool_s,
        args.kind,
        args.effect,
        args.rate_hz,
        args.noise_mm,
        args.seed,
        args.wire,
    )
    print(f"session written: {folder}")
    return 0


# --------------------------------------------------------------------------- demo
def cmd_demo(args: argparse.Namespace) -> int:
    """Headless demo: a session on the mock bench over real transports, fits, a loop PNG."""
    from smabench.fit_cli import usable_rows
    from smabench.physics.identify import fit_loop
    from smabench.plotting import save_loop_png
    from smabench.sessions import load_session

    if args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    sid = time.strftime("demo-%Y%m%d-%H%M%S")
    print(
        f"mock bench ({args.speed:g}× real time): {args.cycles} heating cycles at "
        f"{args.current_a} A under {args.load_kg} kg …",
        flush=True,
    )
    code = main(
        ["run", "--mock", "--mock-speed", str(args.speed), "--load-kg", str(args.load_kg),
         "--cycles", str(args.cycles), "--current-a", str(args.current_a), "--heat-s", "3",
         "--out", str(args.out), "--session-id", sid, "--mock-seed", str(args.seed)]
    )  # fmt: skip
    if code != 0:
        return code
    folder = Path(args.out) / sid
    session = load_session(folder)
    ok, _ = usable_rows(session, session.data["temperature_est_C"])
    temp = session.data["temperature_est_C"][ok]
    pos = session.data["position_mm"][ok]
    fits = [fit_loop(temp, pos, name) for name in ("1", "sigmoid")]
    png = save_loop_png(
        folder / "loop.png",
        temp,
        pos,
        [(f"model {f.model} (nrmse {f.nrmse_percent:.2f} %)", f.predict(temp)) for f in fits],
        title=f"mock bench loop, {args.load_kg} kg",
        xlabel="estimated wire temperature (°C)",
    )
    print(f"loop plot: {png}")
    for f in fits:
        print(
            f"model {f.model} fit: nrmse {f.nrmse_percent:.2f} % of stroke, rmse {f.rmse_mm:.4f} mm"
        )
    return 0


# --------------------------------------------------------------------------- export
def cmd_export(args: argparse.Namespace) -> int:
    from smabench.sessions import export_csv

    columns = [c.strip() for c in args.columns.split(",")] if args.columns else None
    n = export_csv(args.session, args.out, columns)  # streamed chunk by chunk: one table
    print(f"{n} rows written: {args.out}")  # on stderr when the CSV goes to stdout (main)
    return 0


# --------------------------------------------------------------------------- bench
def _load_flexinol(data_dir: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    loops = []
    for f in sorted(data_dir.glob("filtered_data_*.txt")):
        arr = np.loadtxt(f)
        loops.append((f.stem, arr[:, 0], arr[:, 1] * 55.0))
    if not loops:
        raise CliError(f"no filtered_data_*.txt loops in {data_dir} (use --data DIR)")
    return loops


def cmd_bench_model(args: argparse.Namespace) -> int:
    from smabench.physics.model_bench import (
        benchmark_models,
        benchmark_preisach_rows,
        format_table,
    )
    from smabench.physics.plant import benchmark_plant

    loops = _load_flexinol(Path(args.data) if args.data else default_data_dir())
    rows = benchmark_models(loops)
    print(format_table(rows))
    name, t_loop, y_loop = loops[0]
    p = benchmark_preisach_rows(t_loop, y_loop)
    print(
        f"Preisach fit on {p['rows']} rows with reversals (from {name}): {p['fit_s']:.1f} s, "
        f"peak {p['peak_mb']:.0f} MB traced, nrmse {p['nrmse_percent']:.2f} %"
    )
    plant = benchmark_plant()
    print(
        f"\nplant simulation at a 1 kHz step: {plant['steps_per_s']:.3g} steps/s "
        f"= {plant['x_real_time']:.0f}× real time"
    )
    return 0


def cmd_bench_loop(args: argparse.Namespace) -> int:
    from smabench.bench.loop_bench import format_rows, loop_timing

    rows = []
    for firmware in [f.strip() for f in args.firmware.split(",") if f.strip()]:
        for rate in [float(r) for r in args.rates.split(",") if r.strip()]:
            print(f"{firmware} firmware, {rate:g} Hz, {args.duration_s:g} s …", flush=True)
            rows.append(
                loop_timing(rate, firmware, args.duration_s, args.sensor, args.adapter_latency_ms)
            )
    print(format_rows(rows))
    return 0


def cmd_bench_link(args: argparse.Namespace) -> int:
    from smabench.bench.link_bench import format_figures, link_figures

    print(format_figures(link_figures(args.firmware, args.n, args.telemetry_s)))
    return 0


# --------------------------------------------------------------------------- parser
DEMO_CURRENT_WHY = "heats the paper wire through its transformation in a few seconds"
"""Why ``simulate`` and ``demo`` heat at 1.4 A, not at the run schema's default."""
COMMANDS = ("import", "fit", "predict", "simulate", "demo", "export", "mock", "run", "gui",
            "analyze", "characterize", "plan", "firmware", "calibrate", "sensor", "selfsense",
            "bench")


def command_of(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), or None."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``command`` only that command's module is imported and
    registered (each pulls in its own stack: the control law's scipy, the analysis' numba),
    so that a command starts, and a bad option is refused, in a fraction of the time."""

    def want(*names: str) -> bool:
        return command is None or command in names

    p = OneLineParser(
        prog="smabench",
        description="Lab-bench application for shape-memory-alloy wire actuators.",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    p.add_argument("--version", action="version", version=f"smabench {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("import", help="import a measured loop from a text file into a session")
    s.add_argument(
        "file",
        help="a text table: tab, semicolon, comma or white space; metadata, header and units "
        "lines, quoted numbers and decimal commas are found",
    )
    s.add_argument(
        "--columns",
        help="column names in file order, e.g. temperature_C,strain,stress_MPa "
        "(contract names, strain, stress_MPa, temperature_C, voltage_V, skip)",
    )
    s.add_argument("--preview", action="store_true", help="print the layout found and stop")
    s.add_argument("--decimal", choices=[".", ","], help="decimal mark (default: detected)")
    s.add_argument("--wire-length-mm", type=positive(), help="wire length, mm (strain → mm)")
    s.add_argument("--wire-diameter-mm", type=positive(), help="wire diameter, mm (metadata)")
    s.add_argument("--load-kg", type=positive(), help="hanging load, kg (metadata)")
    s.add_argument("--out", help="session folder to create (must not exist)")
    s.set_defaults(func=cmd_import)

    if want("fit", "predict"):
        from smabench.fit_cli import add_commands as add_fit_commands

        add_fit_commands(sub)

    s = sub.add_parser("simulate", help="simulate heating cycles on the plant into a session")
    add_setting_option(s, "--load-kg", "load_kg")
    add_setting_option(s, "--cycles", "protocol.cycles")
    add_setting_option(s, "--current-a", "protocol.current_a", 1.4, DEMO_CURRENT_WHY)
    add_setting_option(s, "--heat-s", "protocol.heat_s", 4.0,
                       "the paper wire's full stroke at 1.4 A from the room's temperature")
    s.add_argument("--cool-s", type=positive(), default=10.0, help="cooling time per cycle, s")
    s.add_argument(
        "--kind",
        choices=["complete", "incomplete", "inner"],
        default="complete",
        help="the paper's excitations: complete, incomplete (reheat early), inner loops",
    )
    s.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="switch on a plant effect (repeatable); see --list-effects",
    )
    s.add_argument("--list-effects", action="store_true", help="list the plant effects and exit")
    add_setting_option(s, "--rate-hz", "rate_hz", 100.0,
                       "a recording's rate; the loop's own is for control")
    add_setting_option(s, "--noise-mm", "sim.noise_mm")
    add_setting_option(s, "--seed", "sim.seed")
    s.add_argument(
        "--wire",
        default="paper",
        choices=["paper", "flexinol-0.38-70c", "flexinol-0.38-90c"],
        help="wire preset",
    )
    s.add_argument("--out", help="session folder to create (must not exist)")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser(
        "demo", help="headless demo: cycles on the mock bench, a session, fits and a loop PNG"
    )
    add_setting_option(s, "--load-kg", "load_kg")
    add_setting_option(s, "--cycles", "protocol.cycles", 3, "a short demo")
    add_setting_option(s, "--speed", "time_scale", 5.0, "a demo runs ahead of the wall clock")
    add_setting_option(s, "--current-a", "protocol.current_a", 1.4, DEMO_CURRENT_WHY)
    add_setting_option(s, "--seed", "mock.seed")
    s.add_argument("--out", default="sessions", help="parent folder (./sessions)")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("export", help="export a session's samples as CSV for spreadsheets")
    s.add_argument("session", help="session folder or CSV")
    s.add_argument("--out", required=True, type=output_file, help="CSV file to write" + OUTPUT_HELP)
    s.add_argument("--columns", help="comma-separated columns to keep, in this order (default all)")
    s.set_defaults(func=cmd_export)

    if want("mock", "run"):
        from smabench.bench.headless import add_commands

        add_commands(sub)
    if want("gui"):
        from smabench.gui.app import add_commands as add_gui_commands

        add_gui_commands(sub)
    if want("analyze"):
        from smabench.analysis.cli import add_commands as add_analysis_commands

        add_analysis_commands(sub)
    if want("characterize"):
        from smabench.characterize.cli import add_commands as add_characterize_commands

        add_characterize_commands(sub)
    if want("plan"):
        from smabench.plan import add_commands as add_plan_commands

        add_plan_commands(sub)
    if want("firmware"):
        from smabench.firmware_cli import add_commands as add_firmware_commands

        add_firmware_commands(sub)
    if want("calibrate", "sensor"):
        from smabench.calibrate import add_commands as add_calibrate_commands

        add_calibrate_commands(sub)
    if want("selfsense"):
        from smabench.selfsense import add_commands as add_selfsense_commands

        add_selfsense_commands(sub)
    if want("bench"):
        _add_bench_commands(sub)
    return p


def _add_bench_commands(sub) -> None:
    s = sub.add_parser("bench", help="benchmarks that print figures")
    bsub = s.add_subparsers(dest="bench", required=True, metavar="WHAT")
    b = bsub.add_parser("model", help="model speed and accuracy, plant speed")
    b.add_argument(
        "--data",
        default=None,
        help="folder with the Flexinol loops (filtered_data_*.txt; default: the shipped pair)",
    )
    b.set_defaults(func=cmd_bench_model)
    b = bsub.add_parser("loop", help="bench loop rate and jitter against the mock bench")
    b.add_argument("--duration-s", type=positive(), default=60.0, help="per run, s (60)")
    b.add_argument("--rates", default="200,500", help="loop rates, Hz (200,500)")
    b.add_argument(
        "--firmware", default="python,emulated", help="current drivers to use (python,emulated)"
    )
    b.add_argument("--sensor", choices=["tcp", "rtu"], default="tcp", help="Modbus transport")
    b.add_argument(
        "--adapter-latency-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="the mock's sensor holds every answer this long, as an FTDI USB/RS-485 adapter "
        "(16 ms by default on a real one; drivers/sensors/README.md)",
    )
    b.set_defaults(func=cmd_bench_loop)
    b = bsub.add_parser("link", help="device link latency and telemetry rate (real transports)")
    b.add_argument(
        "--firmware", choices=["emulated", "python"], default="emulated", help="current driver"
    )
    b.add_argument("-n", type=positive(int), default=500, help="requests per figure (500)")
    b.add_argument("--telemetry-s", type=positive(), default=5.0, help="telemetry count, s")
    b.set_defaults(func=cmd_bench_link)
    from smabench.bench.import_bench import add_bench_import

    add_bench_import(bsub)
    from smabench.analysis.bench import add_bench_analyze
    from smabench.bench.control_bench import add_bench_control
    from smabench.gui.bench_gui import add_bench_gui

    add_bench_control(bsub)
    add_bench_analyze(bsub)
    from smabench.characterize.cli import add_bench_characterize

    add_bench_characterize(bsub)
    from smabench.selfsense_bench import add_bench_selfsense

    add_bench_selfsense(bsub)

    add_bench_gui(bsub, positive())


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(command_of(argv))
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    if getattr(args, "list_effects", False):
        from smabench.physics.plant import EFFECT_DOCS

        for name, doc in EFFECT_DOCS.items():
            print(f"{name:22s} {doc}")
        return 0
    if args.command == "simulate" and not args.out:
        parser.error("simulate needs --out")
    to_stdout = [k for k in OUTPUT_OPTIONS if _is_stdout(getattr(args, k, None))]
    if len(to_stdout) > 1:
        both = " and --".join(to_stdout)
        print(f"smabench {args.command}: error: only one output can be standard output, got "
              f"--{both}", file=sys.stderr)  # fmt: skip
        return EXIT_USAGE
    try:
        if to_stdout:  # the data go to stdout; what the command prints goes to stderr
            from smabench.sessions import data_to_stdout

            with data_to_stdout():
                return int(args.func(args) or 0)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("smabench: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of our stdout went away (`| head`): as cat does
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except USER_ERRORS as exc:
        if args.verbose:
            raise
        msg = one_line(str(exc) or exc.__class__.__name__)
        print(f"smabench {args.command}: error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    except device_errors() as exc:  # a port that cannot be opened, a device that does not answer
        if args.verbose:
            raise
        msg = str(exc) or exc.__class__.__name__
        print(f"smabench {args.command}: device error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    except ImportError as exc:  # a missing GUI library or Qt system library: say what to install
        if args.verbose:
            raise
        print(f"smabench {args.command}: error: {missing_library_hint(exc)}", file=sys.stderr)
        return EXIT_USAGE


def configure_logging(verbose: bool) -> None:
    """The console log: with ``--verbose`` every logger from DEBUG; otherwise one line per
    real problem: smabench's own warnings and errors, its drivers' errors only (a device's
    fault, a lost link: the session's end line says it once). Libraries' lines (pymodbus's "No
    response received after 0 retries" for each late sensor answer, which the session already
    flags) stay off the console."""
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    if not verbose:
        handler.addFilter(_console_record)
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING, handlers=[handler])


def _console_record(record: logging.LogRecord) -> bool:
    name = record.name
    if name.startswith("smabench.drivers"):
        return record.levelno >= logging.ERROR
    return name == "smabench" or name.startswith("smabench.")


OUTPUT_OPTIONS = ("out", "json", "csv", "plot", "predictions")
"""The destinations of option values that may be ``-`` (standard output)."""


def _is_stdout(path: object) -> bool:
    from smabench.sessions import is_stdout

    return isinstance(path, str) and is_stdout(path)


def one_line(text: str) -> str:
    """``text`` with its control characters escaped (a file's bytes quoted in an error message
    must not break the one line on stderr)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def device_errors() -> tuple[type[BaseException], ...]:
    """The drivers' errors: the environment, not a bug (imported only when something failed)."""
    from smabench.bench.headless import MockError
    from smabench.drivers.base import SensorError
    from smabench.drivers.link import LinkError

    return (LinkError, SensorError, MockError)


QT_SYSTEM_PACKAGES = "libegl1 libgl1 libxkbcommon0 libfontconfig1 libdbus-1-3 libglib2.0-0"


def missing_library_hint(exc: ImportError) -> str:
    """One line naming what to install for an ImportError (a module or a shared library)."""
    name = (exc.name or "").split(".")[0]
    if name in ("PySide6", "pyqtgraph", "shiboken6"):
        return (f"{name} is missing: pip install 'PySide6-Essentials==6.11.3' pyqtgraph "
                "(both come with smabench)")  # fmt: skip
    text = str(exc)
    if "failed to map segment" in text or "cannot allocate memory" in text.lower():
        return (f"a shared library could not be loaded for lack of memory ({exc}): the memory "
                "or address space given to this process (ulimit -v, a container's limit) is "
                "too small")  # fmt: skip
    if ".so" in text:
        return (f"Qt could not load a system library ({exc}): "
                f"apt-get install {QT_SYSTEM_PACKAGES}")  # fmt: skip
    return f"cannot import {exc.name or exc}: reinstall smabench (pip install smabench)"


if __name__ == "__main__":
    sys.exit(main())
