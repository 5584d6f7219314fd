"""Characterize sessions: read each (streamed chunk by chunk), run E3097, fit the phase diagram.

One session is one task (:func:`characterize_session`, a plain function of picklable
arguments): :func:`smabench.tasks.run_tasks` runs them on local worker processes or on a Dask
cluster when given a scheduler address; the results are the same either way (each task is
deterministic and the results are put back in the order of the sessions).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from smabench.characterize.e3097 import (
    TEMPERATURE_KEYS,
    BranchResult,
    CharacterizeError,
    CycleStream,
    NoCompleteCycleError,
)
from smabench.sessions import (
    FLAGS_POSITION_INVALID,
    SessionError,
    iter_sample_chunks,
    load_session_meta_check,
    read_header,
    sample_files,
)
from smabench.tasks import SCHEDULER_TIMEOUT_S, run_tasks

log = logging.getLogger(__name__)

DEFAULT_WIRE_LENGTH_MM = 55.0  # the bench's wire (DESIGN §1); stated on stderr when used
DEFAULT_WIRE_DIAMETER_MM = 0.38


@dataclass(frozen=True)
class Overrides:
    """What the command line may set when a session does not say it (units in names)."""

    wire_length_mm: float | None = None
    wire_diameter_mm: float | None = None
    load_mpa: float | None = None


def stress_mpa(load_kg: float, diameter_mm: float) -> float:
    from smabench.physics.wire import Wire
    from smabench.physics.wire import stress_mpa as wire_stress

    return float(wire_stress(load_kg, Wire().with_diameter_mm(diameter_mm)))


def characterize_session(
    path: str,
    overrides: Overrides = Overrides(),  # noqa: B008 - frozen, immutable
    keep_cycles: Sequence[int] | str = (),
) -> dict[str, Any]:
    """E3097 on one session (folder or CSV). Returns the JSON entry of this session plus, under
    ``"_branches"``, the tangent construction of the cycles in ``keep_cycles`` (for plots).

    Raises :class:`CharacterizeError` / :class:`SessionError` (ValueError) on bad input.
    """
    p = Path(path)
    meta = load_session_meta_check(p)
    first = sample_files(p)[0] if p.is_dir() else p
    header = read_header(first)
    want = [c for c in ("t_s", "temperature_C", "temperature_est_C", "position_mm", "flags",
                        "stress_MPa") if c in header]  # fmt: skip
    warnings: list[str] = []
    wire = meta.get("wire") or {}
    length_mm = overrides.wire_length_mm or wire.get("length_mm")
    if not length_mm:
        length_mm = DEFAULT_WIRE_LENGTH_MM
        warnings.append(f"no wire length in the session: {length_mm:g} mm assumed "
                        "(give --wire-length-mm)")  # fmt: skip
    stream = CycleStream(keep_cycles if keep_cycles == "auto" else set(keep_cycles))
    source: str | None = None
    stress: list[float] = []
    files = sample_files(p) if p.is_dir() else [p]
    rows_seen = 0
    n_masked = 0
    for k, data in enumerate(iter_sample_chunks(p, want)):
        if source is None:
            for col, name in (("temperature_C", "measured"), ("temperature_est_C", "estimated")):
                if col in data and np.isfinite(data[col]).sum() >= 3:
                    source = name
                    break
            if source is None:
                raise CharacterizeError(f"{path}: no temperature_C or temperature_est_C values")
        t_c = data["temperature_C" if source == "measured" else "temperature_est_C"]
        position = data["position_mm"].copy()
        if "flags" in data:
            flags = np.nan_to_num(data["flags"]).astype(np.int64)
            position[(flags & FLAGS_POSITION_INVALID) != 0] = np.nan
        n_masked += int((~(np.isfinite(position) & np.isfinite(t_c))).sum())
        if "stress_MPa" in data and np.isfinite(data["stress_MPa"]).any():
            stress.append(float(np.nanmedian(data["stress_MPa"])))
        t_s = data.get("t_s")
        if t_s is None or not np.isfinite(t_s).any():  # a thermometer loop: row order
            t_s = np.arange(rows_seen, rows_seen + len(t_c), dtype=float)
        rows_seen += len(t_c)
        try:
            stream.feed(t_c, position / float(length_mm), t_s, final=k == len(files) - 1)
        except CharacterizeError as exc:
            raise type(exc)(f"{path}: {exc}") from None
    try:
        cycles, kept = stream.result()
    except CharacterizeError as exc:
        raise type(exc)(f"{path}: {exc}") from None
    load_mpa = overrides.load_mpa
    load_from = "command line"
    if load_mpa is None and stress:
        load_mpa, load_from = float(np.median(stress)), "stress_MPa column"
    if load_mpa is None and meta.get("load_kg") is not None:
        d = overrides.wire_diameter_mm or wire.get("diameter_mm")
        if not d:
            d = DEFAULT_WIRE_DIAMETER_MM
            warnings.append(f"no wire diameter in the session: {d:g} mm assumed")
        load_mpa, load_from = stress_mpa(float(meta["load_kg"]), float(d)), "load_kg and diameter"
    if load_mpa is None:
        warnings.append("no load in the session (give --load-mpa): not in the phase diagram")
    for c in cycles:
        c["temperature_source"] = source
    out: dict[str, Any] = {
        "session": str(path),
        "load_MPa": load_mpa,
        "load_source": load_from if load_mpa is not None else None,
        "temperature_source": source,
        "wire_length_mm": float(length_mm),
        "temperature_noise_K": stream.noise_k,
        "temperature_smoothing_samples": stream.window,
        "n_cycles": len(cycles),
        "n_masked_rows": n_masked,
        "warnings": warnings,
        "cycles": cycles,
    }
    if keep_cycles:
        out["_branches"] = {k: v for k, v in kept.items()}
    return out


def characterize_or_skip(
    path: str,
    overrides: Overrides = Overrides(),  # noqa: B008 - frozen, immutable
    keep_cycles: Sequence[int] | str = (),
    include_aborted: bool = False,
) -> dict[str, Any]:
    """:func:`characterize_session`, or ``{"session": path, "skipped": why}`` for a session that
    a campaign folder holds but that has nothing to characterize: an aborted step (status
    ``aborted`` in session.json; a retried step's first try) unless ``include_aborted``, or a
    session with no complete thermal cycle (an incomplete step). Other bad input still raises."""
    meta = load_session_meta_check(path)
    if meta.get("status") == "aborted" and not include_aborted:
        reason = meta.get("end_reason") or meta.get("reason") or "no reason recorded"
        return {"session": str(path), "skipped": f"aborted ({reason})"}
    try:
        return characterize_session(path, overrides, keep_cycles)
    except NoCompleteCycleError as exc:
        why = str(exc)
        prefix = f"{path}: "
        return {"session": str(path), "skipped": why[len(prefix):] if why.startswith(prefix)
                else why}  # fmt: skip


# --------------------------------------------------------------------------- phase diagram
def phase_diagram(sessions: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """Clausius–Clapeyron slopes dσ/dT (MPa/K) of As, Af, Ms, Mf across loads.

    A straight line T = c + k·σ through every cycle's temperature at its session's stress
    (the stress is the set variable); slope = 1/k. Uncertainty (1 σ): the least-squares standard
    error from the scatter when there are more points than two; with exactly two (one cycle per
    load) the per-cycle temperature uncertainty (RMS residual of the tangent lines) propagated.
    None when fewer than two distinct loads.
    """
    loads = {round(s["load_MPa"], 6) for s in sessions if s.get("load_MPa") is not None}
    if len(loads) < 2:
        return None
    out: dict[str, Any] = {}
    for key in TEMPERATURE_KEYS:
        sig, temp, unc = [], [], []
        for s in sessions:
            if s.get("load_MPa") is None:
                continue
            for c in s["cycles"]:
                v = c.get(f"{key}_C")
                if v is not None:
                    sig.append(s["load_MPa"])
                    temp.append(v)
                    u = c.get("temperature_uncertainty_K")
                    unc.append(u if u is not None and u > 0 else math.nan)
        sig_a, temp_a, unc_a = np.array(sig), np.array(temp), np.array(unc)
        if len(set(np.round(sig_a, 6))) < 2:
            out[key] = {"slope_MPa_per_K": None, "uncertainty": None, "n_points": len(sig),
                        "clausius_clapeyron": False,
                        "why_not": "determined at fewer than two loads"}  # fmt: skip
            continue
        A = np.column_stack([np.ones_like(sig_a), sig_a])
        coef, *_ = np.linalg.lstsq(A, temp_a, rcond=None)
        k = float(coef[1])
        n = len(sig_a)
        cov = None
        if n > 2:
            resid = temp_a - A @ coef
            s2 = float(resid @ resid) / (n - 2)
            cov = s2 * np.linalg.inv(A.T @ A)
        if np.isfinite(unc_a).all():
            w = np.diag(1.0 / unc_a**2)
            cov_w = np.linalg.inv(A.T @ w @ A)
            cov = cov_w if cov is None else np.maximum(cov, cov_w)
        dk = math.sqrt(cov[1, 1]) if cov is not None else math.nan
        slope = 1.0 / k if k != 0 else math.nan
        span_mpa = float(sig_a.max() - sig_a.min())
        why = why_not_clausius_clapeyron(slope, k * span_mpa, dk * span_mpa, span_mpa)
        out[key] = {
            "slope_MPa_per_K": slope if math.isfinite(slope) else None,
            "uncertainty": (dk / k**2) if k != 0 and math.isfinite(dk) else None,
            "T_at_0MPa_C": float(coef[0]),
            "n_points": n,
            "shift_K": k * span_mpa,
            "clausius_clapeyron": why is None,
            "why_not": why,
        }
    return out


CC_SLOPE_RANGE_MPA_PER_K = (3.0, 20.0)
"""Clausius–Clapeyron slopes of NiTi wires lie in this range (about 5–10 MPa/K typically)."""
MIN_SHIFT_SIGMAS = 2.0
"""A stress shift is in the data when the fitted temperature change over the loads is at least
this many standard errors from zero."""


def why_not_clausius_clapeyron(slope_mpa_per_k: float, shift_k: float, shift_se_k: float,
                               span_mpa: float) -> str | None:  # fmt: skip
    """None when a fitted dσ/dT reads as a Clausius–Clapeyron slope, else why not: the wrong sign
    (the temperature must rise with the stress), outside :data:`CC_SLOPE_RANGE_MPA_PER_K`, or no
    stress shift in the data (the temperature change over the loads, ``shift_k`` ± ``shift_se_k``
    K over ``span_mpa`` MPa, not distinguishable from zero)."""
    lo, hi = CC_SLOPE_RANGE_MPA_PER_K
    if math.isfinite(shift_se_k) and abs(shift_k) < MIN_SHIFT_SIGMAS * shift_se_k:
        return (f"no stress shift in the data ({shift_k:+.1f} ± {shift_se_k:.1f} K over "
                f"{span_mpa:.0f} MPa)")  # fmt: skip
    if not math.isfinite(slope_mpa_per_k):
        return f"no stress shift in the data ({shift_k:+.1f} K over {span_mpa:.0f} MPa)"
    if slope_mpa_per_k < 0:
        return "wrong sign (the temperature falls as the stress rises)"
    if not lo <= slope_mpa_per_k <= hi:
        return f"outside {lo:g}–{hi:g} MPa/K"
    return None


def characterize_many(
    paths: Sequence[str],
    overrides: Overrides = Overrides(),  # noqa: B008
    keep_cycles: Sequence[int] | str = (),
    scheduler: str | None = None,
    workers: int | None = None,
    scheduler_timeout_s: float = SCHEDULER_TIMEOUT_S,
    include_aborted: bool = False,
) -> dict[str, Any]:
    """The ``smabench characterize`` JSON document for several sessions (plus ``_branches``
    inside each session entry when ``keep_cycles``; strip before writing). Sessions with nothing
    to characterize (:func:`characterize_or_skip`) are listed under ``skipped`` with the reason;
    :class:`NoCompleteCycleError` when every session was skipped."""
    for p in paths:  # every path checked before any work is sent out
        load_session_meta_check(p)
    keep = keep_cycles if isinstance(keep_cycles, str) else tuple(keep_cycles)
    outcomes = run_tasks(
        characterize_or_skip,
        [(str(p), overrides, keep, include_aborted) for p in paths],
        scheduler=scheduler,
        workers=workers,
        scheduler_timeout_s=scheduler_timeout_s,
    )
    results = [r for r in outcomes if "skipped" not in r]
    skipped = [r for r in outcomes if "skipped" in r]
    if not results:
        if len(skipped) == 1:
            raise NoCompleteCycleError(f"{skipped[0]['session']}: {skipped[0]['skipped']}")
        first = skipped[0]
        raise NoCompleteCycleError(f"nothing to characterize: all {len(skipped)} sessions "
                                   f"skipped (first: {first['session']}: {first['skipped']})")
    return {
        "format": "smabench-characterize/1",
        "standard": "ASTM E3097 (tangent-line intersections; see smabench.characterize.e3097)",
        "sessions": results,
        "skipped": skipped,
        "phase_diagram": phase_diagram(results),
    }


def _finite(obj: Any) -> Any:
    """NaN/inf → None all the way down: strict JSON for other tools (null = not determined)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def strip_private(doc: dict[str, Any]) -> dict[str, Any]:
    """The document without plot-only entries (keys starting with '_'), strict JSON values."""
    return _finite({
        **doc,
        "sessions": [
            {k: v for k, v in s.items() if not k.startswith("_")} for s in doc["sessions"]
        ],
    })  # fmt: skip


def branches_of(doc: dict[str, Any]) -> dict[str, dict[int, tuple[BranchResult, BranchResult]]]:
    return {s["session"]: s.get("_branches", {}) for s in doc["sessions"]}


__all__ = [
    "Overrides",
    "SessionError",
    "characterize_many",
    "characterize_session",
    "phase_diagram",
    "run_tasks",
]
