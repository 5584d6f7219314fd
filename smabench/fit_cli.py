"""``smabench fit`` and ``smabench predict``: identify a loop model, test it on data it did not
see, and apply it to another session.

- ``fit SESSION --model M [--holdout F | --test SESSION2] [--json OUT] [--plot PNG]``: fits on
  the session (with ``--holdout F``, on its first 1 − F of the samples in time) and reports the
  error where it was fitted and, held out, where it was not: the model runs along the whole
  temperature history (its memory of reversals included) and is scored on the held-out samples
  only. ``--json`` writes the errors and the fitted model (``model`` key) that ``predict`` reads.
- ``predict --model FITTED.json SESSION --out CSV``: the model along another session's
  temperature: columns ``t_s, position_mm, model_mm``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from smabench.argtypes import OUTPUT_HELP, output_file

log = logging.getLogger(__name__)


class FitCliError(ValueError):
    """Bad input to fit/predict (one line, exit 2)."""


def loop_temperature(session) -> tuple[np.ndarray, str]:
    """The temperature a loop is fitted against: measured if present, else the estimate."""
    for col in ("temperature_C", "temperature_est_C"):
        if session.has(col):
            return session.data[col], col
    raise FitCliError(
        f"{session.path}: no temperature_C or temperature_est_C values to fit a loop against"
    )


def _finite(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.isfinite(t) & np.isfinite(y)


def usable_rows(session, temperature_c: np.ndarray) -> tuple[np.ndarray, int]:
    """(rows a loop is fitted on, rows masked): the bench records rows whose position its sensor
    flagged invalid (``flags`` & :data:`~smabench.sessions.FLAGS_POSITION_INVALID`, the value may
    still be there) or left empty; those rows are masked, not refused."""
    from smabench.sessions import FLAGS_POSITION_INVALID

    position_mm = session.data["position_mm"]
    ok = _finite(temperature_c, position_mm)
    if session.has("flags"):
        flags = np.nan_to_num(np.asarray(session.data["flags"], dtype=float)).astype(np.int64)
        ok &= (flags & FLAGS_POSITION_INVALID) == 0
    return ok, int((~ok).sum())


def cmd_fit(args: argparse.Namespace) -> int:
    from smabench.physics.identify import MODELS, fit_loop, model_document, nrmse_on
    from smabench.sessions import atomic_write_json, load_session

    if args.model not in MODELS:
        raise FitCliError(f"unknown model {args.model!r}; choose from {', '.join(MODELS)}")
    if args.holdout is not None and not 0.05 <= args.holdout <= 0.8:
        raise FitCliError(f"--holdout must be in 0.05 … 0.8, got {args.holdout}")
    if args.holdout is not None and args.test:
        raise FitCliError("give --holdout or --test, not both")
    session = load_session(args.session)
    temperature_c, tcol = loop_temperature(session)
    position_mm = session.data["position_mm"]
    ok, n_masked = usable_rows(session, temperature_c)
    t_all, y_all = temperature_c[ok], position_mm[ok]
    n_fit = t_all.size
    if args.holdout is not None:
        n_fit = int(round(t_all.size * (1.0 - args.holdout)))
    fit = fit_loop(t_all[:n_fit], y_all[:n_fit], args.model)
    report: dict = {
        "model": fit.model,
        "session": str(session.path),
        "temperature_column": tcol,
        "n_points": int(fit.n_points),
        "n_masked": n_masked,
        "rmse_mm": float(fit.rmse_mm),
        "nrmse_percent": float(fit.nrmse_percent),
        "ard_percent": float(fit.ard_percent),
        "parameters": {k: float(v) for k, v in fit.parameters.items()},
    }
    print(f"model {fit.model} on {session.path} ({fit.n_points} points, vs {tcol})")
    if n_masked:
        print(f"  {n_masked} row(s) masked: position flagged invalid by the sensor or empty")
    for k, v in report["parameters"].items():
        print(f"  {k:>24s} = {v:.6g}")
    print(
        f"  rmse = {fit.rmse_mm:.5f} mm   nrmse = {fit.nrmse_percent:.3f} % of stroke   "
        f"ard = {fit.ard_percent:.3f} %"
    )
    if args.holdout is not None:
        held = np.arange(t_all.size) >= n_fit
        report["holdout"] = {
            "fraction": args.holdout,
            "n_points": int(held.sum()),
            "nrmse_percent": nrmse_on(fit, t_all, y_all, held),
        }
        print(f"  held out: the last {held.sum()} samples ({args.holdout:.0%}): nrmse = "
              f"{report['holdout']['nrmse_percent']:.3f} % of their stroke")  # fmt: skip
    if args.test:
        other = load_session(args.test)
        t2, _ = loop_temperature(other)
        y2 = other.data["position_mm"]
        ok2, _ = usable_rows(other, t2)
        report["test"] = {
            "session": str(other.path),
            "n_points": int(ok2.sum()),
            "nrmse_percent": nrmse_on(fit, t2[ok2], y2[ok2]),
        }
        print(f"  on {other.path}: nrmse = {report['test']['nrmse_percent']:.3f} % of stroke")
    if args.json:
        report["fitted"] = model_document(fit)
        atomic_write_json(args.json, report)
        print(f"json written: {args.json}")
    if args.plot:
        from smabench.plotting import save_loop_png

        save_loop_png(
            args.plot,
            t_all,
            y_all,
            [(f"model {fit.model} (nrmse {fit.nrmse_percent:.2f} %)", fit.predict(t_all))],
            title=f"{session.path.name}",
        )
        print(f"plot written: {args.plot}")
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    from smabench.physics.identify import fit_from_document
    from smabench.sessions import atomic_write, load_session

    try:
        doc = json.loads(Path(args.model).read_text(encoding="utf-8"))
    except OSError as exc:
        raise FitCliError(f"cannot read {args.model}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise FitCliError(f"{args.model}: not JSON ({exc.msg}, line {exc.lineno})") from None
    fit = fit_from_document(doc.get("fitted", doc) if isinstance(doc, dict) else doc)
    session = load_session(args.session)
    temperature_c, tcol = loop_temperature(session)
    t_s = session.data["t_s"]
    position = session.data["position_mm"] if session.has("position_mm") else None
    ok = np.isfinite(temperature_c)
    model_mm = np.full(temperature_c.size, np.nan)
    model_mm[ok] = fit.predict(temperature_c[ok])
    lines = ["t_s,position_mm,model_mm"]
    for k in range(t_s.size):
        pos = "" if position is None or not np.isfinite(position[k]) else f"{position[k]:.6f}"
        mod = "" if not np.isfinite(model_mm[k]) else f"{model_mm[k]:.6f}"
        lines.append(f"{t_s[k]:.6f},{pos},{mod}")
    atomic_write(Path(args.out), "\n".join(lines) + "\n")
    msg = f"model {fit.model} along {session.path} ({tcol}): {args.out}"
    if position is not None:
        both = np.isfinite(model_mm) & np.isfinite(position)
        if both.sum() >= 2:
            err = model_mm[both] - position[both]
            nrmse = 100.0 * float(np.sqrt(np.mean(err**2)) / (np.ptp(position[both]) or 1.0))
            msg += f"; nrmse {nrmse:.3f} % of stroke"
    print(msg)
    return 0


def add_commands(sub) -> None:
    """Register ``fit`` and ``predict`` on the CLI's subparsers."""
    s = sub.add_parser("fit", help="identify a loop model on a session and report its error")
    s.add_argument("session", help="session folder or CSV")
    s.add_argument("--model", default="1", help="1, 2, preisach or sigmoid (default 1)")
    held = s.add_mutually_exclusive_group()
    held.add_argument("--holdout", type=float, metavar="FRACTION",
                      help="fit on the first 1 − FRACTION of the samples (in time), report the "
                           "error on the rest (0.05 … 0.8)")  # fmt: skip
    held.add_argument("--test", metavar="SESSION", help="also report the error on this session")
    s.add_argument("--json", type=output_file,
                   help="write the errors, parameters and the fitted model here" + OUTPUT_HELP)
    s.add_argument("--plot", type=output_file,
                   help="write a PNG overlaying measured and model loops here" + OUTPUT_HELP)
    s.set_defaults(func=cmd_fit)

    s = sub.add_parser("predict", help="apply a fitted model (fit --json) to another session")
    s.add_argument("session", help="session folder or CSV")
    s.add_argument("--model", required=True, metavar="FITTED.json", help="from fit --json")
    s.add_argument("--out", required=True, metavar="CSV", type=output_file,
                   help="t_s, position_mm, model_mm" + OUTPUT_HELP)
    s.set_defaults(func=cmd_predict)
