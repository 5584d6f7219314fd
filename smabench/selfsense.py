"""`smabench selfsense calibrate|estimate`: learning the resistance → position map from recorded
sessions and estimating position from the resistance of any session (issue 26). The maps, the
calibration and the online estimator are :mod:`smabench.physics.selfsense` (the bench runs the
estimator live); this module reads sessions and writes files."""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from smabench.argtypes import OUTPUT_HELP, output_file, positive
from smabench.physics.selfsense import (
    BRANCH_NAMES,
    COOLING,
    FILTER_TAU_COOLING_S,
    FILTER_TAU_S,
    FOLDS_MAX,
    HEATING,
    MAPS,
    MIN_BRANCH_ROWS,
    MIN_CURRENT_A,
    MIN_ROWS,
    POLY_DEGREE,
    PROBE_LEVEL_A,
    SCHEMA_VERSION,
    BranchMap,
    SelfSenseCalibration,
    SelfSenseError,
    SelfSenseEstimator,
    branch_of,
    fit_branch_map,
    fit_thermal_map,
    load_calibration,
    resistance_from,
)

__all__ = [  # the maps and the estimator are smabench.physics.selfsense's, re-exported
    "BRANCH_NAMES",
    "BranchMap",
    "COOLING",
    "FILTER_TAU_COOLING_S",
    "FILTER_TAU_S",
    "FOLDS_MAX",
    "HEATING",
    "MAPS",
    "MIN_BRANCH_ROWS",
    "MIN_CURRENT_A",
    "MIN_ROWS",
    "POLY_DEGREE",
    "PROBE_LEVEL_A",
    "SCHEMA_VERSION",
    "SelfSenseCalibration",
    "SelfSenseError",
    "SelfSenseEstimator",
    "SessionArrays",
    "SessionEstimate",
    "add_commands",
    "branch_of",
    "calibrate",
    "estimate_session",
    "fit_branch_map",
    "load_calibration",
    "resistance_from",
    "session_arrays",
]


@dataclass(frozen=True)
class SessionArrays:
    """What self-sensing reads of one session: arrays of equal length and the session's facts.

    ``position_mm`` is NaN where the laser's sample is invalid (flagged or absent)."""

    t_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    position_mm: np.ndarray
    cycle: np.ndarray
    source: str = ""
    load_kg: float | None = None
    wire: dict[str, Any] | None = None
    temperature_c: np.ndarray | None = None
    """The bench's heat-balance temperature (``temperature_est_C``), °C; None when not recorded."""


def session_arrays(session: Any, need_position: bool = True) -> SessionArrays:
    """The columns self-sensing needs from a loaded session or a session path (the edge to
    :func:`smabench.sessions.load_session`). Refuses (``SelfSenseError``) a session without
    ``current_A``/``voltage_V`` values."""
    from smabench.sessions import FLAGS_POSITION_INVALID, Session, load_session

    if not isinstance(session, Session):
        session = load_session(session)
    name = str(session.path)
    missing = [c for c in ("current_A", "voltage_V") if not session.has(c)]
    if missing:
        raise SelfSenseError(
            f"{name}: no {' or '.join(missing)} values: self-sensing needs the wire voltage and "
            "the current"
        )
    d = session.data
    n = len(d["t_s"])
    pos = np.asarray(d.get("position_mm", np.full(n, np.nan)), dtype=float).copy()
    if "flags" in d:
        flags = np.nan_to_num(np.asarray(d["flags"], dtype=float), nan=0.0).astype(np.int64)
        pos[(flags & FLAGS_POSITION_INVALID) != 0] = np.nan
    cycle = d.get("cycle")
    cyc = (np.zeros(n, dtype=np.int64) if cycle is None
           else np.nan_to_num(np.asarray(cycle, dtype=float), nan=-1).astype(np.int64))  # fmt: skip
    meta = session.meta
    temp = d.get("temperature_est_C")
    return SessionArrays(
        np.asarray(d["t_s"], dtype=float), np.asarray(d["current_A"], dtype=float),
        np.asarray(d["voltage_V"], dtype=float), pos, cyc, name,
        None if meta.get("load_kg") is None else float(meta["load_kg"]), meta.get("wire"),
        None if temp is None else np.asarray(temp, dtype=float),
    )  # fmt: skip


def _filtered(s: SessionArrays, params: SelfSenseCalibration) -> tuple[np.ndarray, np.ndarray]:
    """(filtered R, branch) per row, exactly as the estimator filters (NaN where no R)."""
    r = resistance_from(s.current_a, s.voltage_v, params.min_current_a)
    br = branch_of(s.current_a, params.probe_level_a)
    out = np.full(len(r), np.nan)
    rf, t_last = math.nan, math.nan
    taus = (params.filter_tau_s, params.filter_tau_cooling_s)
    for k, (rv, tv, bv) in enumerate(zip(r.tolist(), s.t_s.tolist(), br.tolist(), strict=True)):
        if rv != rv or tv != tv:
            continue
        if rf != rf:
            rf = rv
        else:
            tau = taus[bv]
            a = 1.0 if tau <= 0 else -math.expm1(-max(tv - t_last, 0.0) / tau)
            rf = rf + a * (rv - rf)
        t_last = tv
        out[k] = rf
    return out, br


def _runs(mask_rows: np.ndarray, branch: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Runs of one branch over the rows with R: (branch, row indices)."""
    rows = np.flatnonzero(mask_rows)
    if len(rows) == 0:
        return []
    b = branch[rows]
    cut = np.flatnonzero(np.diff(b)) + 1
    return [(int(b[p[0]]), rows[p]) for p in np.split(np.arange(len(rows)), cut)]


@dataclass
class _Learn:
    """Learning rows of one branch over all sessions: R_f, x, group (session, cycle)."""

    r: list[np.ndarray] = field(default_factory=list)
    x: list[np.ndarray] = field(default_factory=list)
    g: list[np.ndarray] = field(default_factory=list)


def calibrate(
    sessions: Sequence[Any],
    *,
    min_current_a: float = MIN_CURRENT_A,
    probe_level_a: float = PROBE_LEVEL_A,
    filter_tau_s: float = FILTER_TAU_S,
    filter_tau_cooling_s: float = FILTER_TAU_COOLING_S,
    fit: str = "poly",
    degree: int = POLY_DEGREE,
    reversal: bool = True,
    map: str = "branches",
) -> SelfSenseCalibration:
    """Learn the map from sessions recorded with the laser (paths, loaded sessions or
    :class:`SessionArrays`). Refuses (``SelfSenseError``) sessions without voltage/current,
    fewer than :data:`MIN_ROWS` rows with R and a valid position, or a branch without its
    transformation."""
    if not sessions:
        raise SelfSenseError("no sessions to calibrate from")
    if map not in MAPS:
        raise SelfSenseError(f"map {map!r}: one of {', '.join(MAPS)}")
    arrays = [s if isinstance(s, SessionArrays) else session_arrays(s) for s in sessions]
    if min_current_a <= 0 or probe_level_a <= min_current_a:
        raise SelfSenseError("need 0 < min_current_a < probe_level_a")
    if not (0 <= filter_tau_s < math.inf and 0 <= filter_tau_cooling_s < math.inf):
        raise SelfSenseError("filter time constants must be finite and ≥ 0 s")
    dummy = BranchMap("poly", 0.0, 1.0, 1, 1, coeffs=(0.0,))
    params = SelfSenseCalibration(
        dummy, dummy, min_current_a, probe_level_a, filter_tau_s, filter_tau_cooling_s, reversal
    )
    filt = [_filtered(s, params) for s in arrays]
    usable = [np.isfinite(rf) & np.isfinite(s.position_mm)
              for s, (rf, _) in zip(arrays, filt, strict=True)]  # fmt: skip
    for s, ok in zip(arrays, usable, strict=True):
        if int(ok.sum()) < MIN_ROWS:
            raise SelfSenseError(
                f"{s.source or 'session'}: {int(ok.sum())} rows with a resistance (current ≥ "
                f"{min_current_a:g} A) and a valid position; at least {MIN_ROWS} needed"
            )
    x_all = np.concatenate([s.position_mm[ok] for s, ok in zip(arrays, usable, strict=True)])
    r_all = np.concatenate([rf[ok] for (rf, _), ok in zip(filt, usable, strict=True)])
    x_lo, x_hi = (float(v) for v in np.percentile(x_all, [1.0, 99.0]))
    if not x_hi > x_lo:
        raise SelfSenseError("the laser's position does not move in these sessions")
    mid = (x_lo + 0.25 * (x_hi - x_lo), x_lo + 0.75 * (x_hi - x_lo))
    # direction of the position (x_direction) and of R (forward) on each branch
    dx = [0.0, 0.0]
    slope_rx: list[list[np.ndarray]] = [[], []]
    for s, (rf, br), ok in zip(arrays, filt, usable, strict=True):
        for b, rows in _runs(np.isfinite(rf), br):
            xs = s.position_mm[rows]
            good = np.flatnonzero(np.isfinite(xs))
            if len(good) >= 2:
                dx[b] += float(xs[good[-1]] - xs[good[0]])
        inside = ok & (s.position_mm > mid[0]) & (s.position_mm < mid[1])
        for b in (HEATING, COOLING):
            sel = inside & (br == b)
            slope_rx[b].append(np.stack([rf[sel], s.position_mm[sel]]))
    forward, x_dir = [1, 1], [1, 1]
    for b in (HEATING, COOLING):
        rx = np.concatenate(slope_rx[b], axis=1)
        if rx.shape[1] < 3 or dx[b] == 0.0 or np.ptp(rx[0]) == 0:
            raise SelfSenseError(
                f"no {BRANCH_NAMES[b]} through the transformation in these sessions (the "
                f"position never crosses mid-stroke while {BRANCH_NAMES[b]})"
            )
        x_dir[b] = 1 if dx[b] > 0 else -1
        cov = float(np.mean((rx[0] - rx[0].mean()) * (rx[1] - rx[1].mean())))
        forward[b] = x_dir[b] * (1 if cov > 0 else -1)
    # learning rows: each run from its backward extreme of R to its forward extreme after it
    learn = [_Learn(), _Learn()]
    for si, (s, (rf, br)) in enumerate(zip(arrays, filt, strict=True)):
        for b, rows in _runs(np.isfinite(rf), br):
            u = forward[b] * rf[rows]
            i_b = int(np.argmin(u))
            i_f = i_b + int(np.argmax(u[i_b:]))
            seg = rows[i_b : i_f + 1]
            seg = seg[np.isfinite(s.position_mm[seg])]
            learn[b].r.append(rf[seg])
            learn[b].x.append(s.position_mm[seg])
            learn[b].g.append(si * 1_000_000 + s.cycle[seg])
    data = []
    for b in (HEATING, COOLING):
        r = np.concatenate(learn[b].r)
        if len(r) < MIN_BRANCH_ROWS:
            raise SelfSenseError(
                f"{len(r)} {BRANCH_NAMES[b]} rows through the transformation; at least "
                f"{MIN_BRANCH_ROWS} needed"
            )
        data.append((r, np.concatenate(learn[b].x), np.concatenate(learn[b].g)))

    noise = _filtered_noise_ohm(arrays, params)

    def maps(exclude: np.ndarray | None) -> tuple[BranchMap, BranchMap]:
        out = []
        for b, (r, x, g) in enumerate(data):
            keep = np.ones(len(r), bool) if exclude is None else ~np.isin(g, exclude)
            m = fit_branch_map(r[keep], x[keep], forward[b], x_dir[b], fit, degree)
            out.append(replace(m, noise_ohm=noise[b]))
        return out[0], out[1]

    heating, cooling = maps(None)
    thermal = None
    if all(s.temperature_c is not None for s in arrays):  # recorded by the bench
        temps = np.concatenate([s.temperature_c[ok] for s, ok in zip(arrays, usable, strict=True)])
        if int(np.isfinite(temps).sum()) >= MIN_ROWS:
            thermal = fit_thermal_map(
                np.concatenate([rf[ok] for (rf, _), ok in zip(filt, usable, strict=True)]),
                temps,
                x_all,
            )
    if map == "thermal" and thermal is None:
        raise SelfSenseError("the thermal map needs the bench's temperature_est_C in every "
                             f"session (at least {MIN_ROWS} rows with it)")  # fmt: skip
    base = replace(params, heating=heating, cooling=cooling, thermal=thermal, map=map)
    rms, heldout = _heldout_rms(arrays, filt, usable, data, base, maps)
    same_load = {s.load_kg for s in arrays}
    return replace(
        base,
        heating=replace(heating, rms_mm=rms[HEATING], heldout=heldout),
        cooling=replace(cooling, rms_mm=rms[COOLING], heldout=heldout),
        r_range_ohm=(float(np.min(r_all)), float(np.max(r_all))),
        x_range_mm=(x_lo, x_hi),
        sessions=tuple(
            {
                "path": s.source,
                "load_kg": s.load_kg,
                "wire": s.wire,
                "rows": int(len(s.t_s)),
                "rows_used": int(ok.sum()),
            }
            for s, ok in zip(arrays, usable, strict=True)
        ),  # fmt: skip
        load_kg=same_load.pop() if len(same_load) == 1 else None,
        wire=arrays[0].wire if all(s.wire == arrays[0].wire for s in arrays) else None,
    )


def _filtered_noise_ohm(
    arrays: Sequence[SessionArrays], params: SelfSenseCalibration
) -> list[float]:
    """Per branch, the standard deviation of the filtered R's noise, Ω: the raw R's sample-to-
    sample noise (median absolute successive difference, robust to the motion) through the
    first-order filter's noise gain √(a/(2 − a)), a = 1 − exp(−Δt/τ)."""
    out = []
    for b, tau in ((HEATING, params.filter_tau_s), (COOLING, params.filter_tau_cooling_s)):
        diffs, dts = [], []
        for s in arrays:
            r = resistance_from(s.current_a, s.voltage_v, params.min_current_a)
            ok = np.isfinite(r) & (branch_of(s.current_a, params.probe_level_a) == b)
            pair = ok[1:] & ok[:-1]
            diffs.append(np.diff(r)[pair])
            dts.append(np.diff(s.t_s)[pair])
        d = np.concatenate(diffs)
        if len(d) < 2:
            out.append(0.0)
            continue
        sigma = float(np.median(np.abs(d - np.median(d)))) / (0.6745 * math.sqrt(2.0))
        dt = float(np.median(np.concatenate(dts)))
        a = 1.0 if tau <= 0 or dt <= 0 else -math.expm1(-dt / tau)
        out.append(sigma * math.sqrt(a / (2.0 - a)))
    return out


def _heldout_rms(arrays, filt, usable, data, base, maps) -> tuple[list[float], bool]:
    """Per-branch RMS error of the estimator, each cycle estimated with maps learned without
    it (cycles in at most :data:`FOLDS_MAX` folds) when there are ≥ 2 cycles, else in-sample."""
    groups = np.unique(np.concatenate([g for _, _, g in data]))
    heldout = len(groups) >= 2
    folds = np.array_split(groups, min(FOLDS_MAX, len(groups))) if heldout else [groups]
    fold_maps = [maps(f) if heldout else (base.heating, base.cooling) for f in folds]
    fold_of = {int(g): k for k, f in enumerate(folds) for g in f.tolist()}
    sq, n = [0.0, 0.0], [0, 0]
    for si, (s, (_, br), ok) in enumerate(zip(arrays, filt, usable, strict=True)):
        est = SelfSenseEstimator(base)
        key = si * 1_000_000 + s.cycle
        x = np.full(len(s.t_s), np.nan)
        cut = np.concatenate(([0], np.flatnonzero(np.diff(key)) + 1, [len(key)]))
        for a, z in zip(cut[:-1], cut[1:], strict=True):
            k = fold_of.get(int(key[a]), 0)
            est._set_maps(*fold_maps[k])
            x[a:z] = est.estimate(s.t_s[a:z], s.current_a[a:z], s.voltage_v[a:z])
        err = x - s.position_mm
        for b in (HEATING, COOLING):
            e = err[ok & (br == b) & np.isfinite(err)]
            sq[b] += float(np.sum(e * e))
            n[b] += len(e)
    return [math.sqrt(sq[b] / n[b]) if n[b] else math.nan for b in (0, 1)], heldout


# --------------------------------------------------------------------------- estimation
@dataclass(frozen=True)
class SessionEstimate:
    """``t_s``, the laser's ``position_mm`` (NaN where absent/invalid), ``position_est_mm``;
    ``rms_mm``: RMS of the estimate against the laser where both exist (NaN if none)."""

    t_s: np.ndarray
    position_mm: np.ndarray
    position_est_mm: np.ndarray
    rms_mm: float
    rows_compared: int


def estimate_session(calibration: SelfSenseCalibration, session: Any) -> SessionEstimate:
    """Run the estimator over a session (path, loaded session or :class:`SessionArrays`)."""
    s = session if isinstance(session, SessionArrays) else session_arrays(session)
    est = SelfSenseEstimator(calibration).estimate(
        s.t_s, s.current_a, s.voltage_v, s.temperature_c
    )  # the bench's, if recorded
    both = np.isfinite(est) & np.isfinite(s.position_mm)
    n = int(both.sum())
    rms = float(np.sqrt(np.mean((est[both] - s.position_mm[both]) ** 2))) if n else math.nan
    return SessionEstimate(s.t_s, s.position_mm, est, rms, n)


# --------------------------------------------------------------------------- CLI
def cmd_calibrate(args: argparse.Namespace) -> int:
    from smabench.sessions import atomic_write

    cal = calibrate(
        args.sessions,
        min_current_a=args.min_current_a,
        probe_level_a=args.probe_level_a,
        filter_tau_s=args.filter_tau_s,
        filter_tau_cooling_s=args.filter_tau_cooling_s,
        map=args.map,
    )
    atomic_write(args.out, cal.to_json())
    kind = "held out by cycle" if cal.heating.heldout else "in-sample (one cycle)"
    print(f"stroke {cal.stroke_mm:.3f} mm, R {cal.r_range_ohm[0]:.5f} … "
          f"{cal.r_range_ohm[1]:.5f} Ω; RMS error {kind}:")  # fmt: skip
    for b, name in enumerate(BRANCH_NAMES):
        m = cal.branch(b)
        print(f"  {name}: {m.rms_mm:.4f} mm = {cal.percent_of_stroke(m.rms_mm):.2f} % of stroke "
              f"({m.rows} learning rows)")  # fmt: skip
    if cal.thermal is not None:
        th = cal.thermal
        print(f"  thermal map: {th.rms_mm:.4f} mm = {cal.percent_of_stroke(th.rms_mm):.2f} % of "
              f"stroke in-sample, temperature coefficient {th.tcr_per_k:.2e} /K")  # fmt: skip
    print(f"estimator reads the {cal.map} map{'s' if cal.map == 'branches' else ''}")
    print(f"calibration written: {args.out}")
    return 0


def cmd_estimate(args: argparse.Namespace) -> int:
    from smabench.sessions import atomic_write, rows_from_arrays

    cal = load_calibration(args.calibration)
    s = session_arrays(args.session)
    res = estimate_session(cal, s)
    if not np.isfinite(res.position_est_mm).any():
        raise SelfSenseError(
            f"{args.session}: no row with a resistance (current ≥ {cal.min_current_a:g} A)"
        )
    cols = ["t_s", "position_mm", "position_est_mm"]
    data = {"t_s": res.t_s, "position_mm": res.position_mm,
            "position_est_mm": np.round(res.position_est_mm, 6)}  # fmt: skip

    def write(fh) -> None:
        fh.write(",".join(cols) + "\n")
        for row in rows_from_arrays(data, cols):
            fh.write(",".join(row) + "\n")

    atomic_write(args.out, write)
    if s.load_kg is not None and cal.load_kg is not None and s.load_kg != cal.load_kg:
        print(f"note: calibrated at {cal.load_kg:g} kg, this session ran at {s.load_kg:g} kg")
    if res.rows_compared:
        print(f"RMS error against the laser: {res.rms_mm:.4f} mm = "
              f"{cal.percent_of_stroke(res.rms_mm):.2f} % of stroke "
              f"({res.rows_compared} rows)")  # fmt: skip
    else:
        print("no laser position in this session to compare with")
    print(f"{len(res.t_s)} rows written: {args.out}")
    return 0


def add_commands(sub: Any) -> None:
    """Register ``selfsense calibrate|estimate`` on the CLI's subparsers."""
    p = sub.add_parser("selfsense", help="position from the wire's resistance (self-sensing)")
    ssub = p.add_subparsers(dest="what", required=True, metavar="WHAT")
    s = ssub.add_parser(
        "calibrate", help="learn the resistance → position map from sessions with the laser"
    )
    s.add_argument("sessions", nargs="+", metavar="SESSION", help="session folders (or CSVs)")
    s.add_argument("--out", required=True, type=output_file,
                   help="calibration JSON to write" + OUTPUT_HELP)  # fmt: skip
    s.add_argument("--min-current-a", type=positive(), default=MIN_CURRENT_A,
                   help=f"no resistance below this current, A ({MIN_CURRENT_A:g})")  # fmt: skip
    s.add_argument(
        "--probe-level-a",
        type=positive(),
        default=PROBE_LEVEL_A,
        help=f"heating above this current, cooling at or below, A ({PROBE_LEVEL_A:g})",
    )
    s.add_argument(
        "--filter-tau-s",
        type=float,
        default=FILTER_TAU_S,
        help=f"R filter time constant while heating, s ({FILTER_TAU_S:g})",
    )
    s.add_argument(
        "--map",
        choices=MAPS,
        default="branches",
        help="what the estimator reads: the branch maps on R (open-loop recordings) "
        "or the thermal map, R at a reference temperature from the bench's heat "
        "balance (control on the estimate; needs temperature_est_C)",
    )
    s.add_argument("--filter-tau-cooling-s", type=float, default=FILTER_TAU_COOLING_S,
                   help=f"... while cooling, s ({FILTER_TAU_COOLING_S:g})")  # fmt: skip
    s.set_defaults(func=cmd_calibrate)
    s = ssub.add_parser("estimate", help="estimate the position of a session from its resistance")
    s.add_argument("session", metavar="SESSION", help="session folder (or CSV)")
    s.add_argument("--calibration", required=True, metavar="CAL.json",
                   help="from smabench selfsense calibrate")  # fmt: skip
    s.add_argument(
        "--out",
        required=True,
        type=output_file,
        help="CSV to write: t_s,position_mm,position_est_mm" + OUTPUT_HELP,
    )
    s.set_defaults(func=cmd_estimate)
