"""Analysis outputs: the JSON summary, the predictions CSV, a Markdown report with PNG plots."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from smabench.analysis.candidates import cause_text
from smabench.analysis.core import (
    ALPHA,
    ALPHA_SEPARATION,
    MIN_GAIN,
    TIE_NOISE,
    Analysis,
    headline_key,
    parameter_flags,
    physical_parameters,
)


def _clean(x):
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        f = float(x)
        return f if math.isfinite(f) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def loop_shift(an: Analysis) -> dict | None:
    """Check for stress_shift: mid-stroke temperatures of each branch per load, and the stress
    rate they imply. Thermometer loops: the measured temperature (model-free). Current-driven
    sessions: the temperature the stress_shift model estimates from the current (the
    baseline's would be bent by the fit to absorb the shift it cannot describe)."""
    pts = []
    source = "stress_shift" if "stress_shift" in an.preds else "baseline"
    for s in an.prob.sessions:
        if s.stress_mpa is None:
            continue
        temp = s.temp if s.kind == "thermo" else an.preds[source][s.name].temp_c
        pos = s.pos
        lo, hi = np.nanpercentile(pos, [2, 98])
        mid = 0.5 * (lo + hi)
        d = np.concatenate(([0.0], np.diff(temp)))
        out = {}
        for tag, sign in (("heating", 1), ("cooling", -1)):
            on = np.sign(d) == sign
            with np.errstate(invalid="ignore"):
                near = on & (np.abs(pos - mid) < 0.1 * (hi - lo))
            if near.sum() >= 2:
                out[tag] = float(np.median(temp[near]))
        if len(out) == 2:
            pts.append((s.stress_mpa, 0.5 * (out["heating"] + out["cooling"]), out))
    if len(pts) < 2 or len({round(p[0]) for p in pts}) < 2:
        return None
    sig = np.array([p[0] for p in pts])
    tm = np.array([p[1] for p in pts])
    slope_k_per_mpa = float(np.polyfit(sig, tm, 1)[0])
    return {
        "per_session": [
            {"stress_MPa": p[0], "mid_heating_C": p[2]["heating"], "mid_cooling_C": p[2]["cooling"]}
            for p in pts
        ],
        "temperature": "measured" if all(s.kind == "thermo" for s in an.prob.sessions)
        else f"estimated by the {source} model",
        "shift_k_per_mpa": slope_k_per_mpa,
        "stress_rate_mpa_per_k": 1.0 / slope_k_per_mpa if slope_k_per_mpa > 0 else None,
    }


def summary(an: Analysis) -> dict:
    """The JSON document (keys: cause, runner_up, baseline/extended held-out RMSE, gain, …)."""
    v = an.result
    cause = v["cause"]
    causes = v.get("causes") or []
    ext_model = causes[-1]["model"] if causes else (
        cause if cause in an.fits else v.get("leader"))  # fmt: skip
    base = an.rmse["baseline"]
    ext = an.rmse.get(ext_model, base) if ext_model else base
    cands = {}
    for c in an.prob.candidates:
        row = v["rows"][c]
        params = physical_parameters(an, c)
        key = headline_key(an, c)
        cands[c] = {
            "heldout_rmse_mm": an.rmse[c],
            "gain": row["gain"],
            "unit_gain": row["unit_gain"],
            "p_value": row["p_value"],
            "significant": row["significant"],
            "parameter": {key: params[key]},
            "train_rmse_mm": float(np.mean([f.train_rmse_mm for f in an.fits[c]])),
            "fit_seconds": an.timing.get(c),
        }
        for k in ("ruled_out", "on_top"):
            if k in row:
                cands[c][k] = row[k]
    ext_params = physical_parameters(an, ext_model) if ext_model else {}
    base_params = physical_parameters(an, "baseline")
    flags = parameter_flags(an, "baseline", base_params)
    if ext_model and ext_model != "baseline":
        flags += parameter_flags(an, ext_model, ext_params)
    notes = sorted({n for s in an.prob.sessions for n in s.notes})
    out = {
        "cause": cause,
        "causes": [
            {"cause": c["cause"], "incremental_gain": c["gain"], "p_value": c["p_value"],
             "over": c["over"], "parameter": {headline_key(an, c["cause"]):
                                              ext_params.get(headline_key(an, c["cause"]))}}
            for c in causes
        ],  # fmt: skip
        "flags": flags,
        "assumed": notes,
        "runner_up": v["runner_up"],
        "reason": v["reason"],
        "extended_model": ext_model,
        "baseline_heldout_rmse_mm": base,
        "extended_heldout_rmse_mm": ext,
        "gain": 1.0 - ext / base if base > 0 else 0.0,
        "parameters": ext_params,
        "baseline_parameters": base_params,
        "kinetics": v.get("kinetics"),
        "candidates": cands,
        "skipped_candidates": an.prob.skipped,
        "test": {
            "kind": "one-sided paired test on per-unit held-out RMSE: the smaller of the "
            "Wilcoxon signed-rank and the log-ratio t-test p, × 2 (Bonferroni)",
            "alpha": ALPHA,
            "alpha_separation": ALPHA_SEPARATION,
            "ties": f"units where both models stay below {TIE_NOISE:g} × the noise are left out",
            "units": len(an.units),
            "min_gain": MIN_GAIN,
            "structured_baseline": v["structured"],
            "floor_mm": v["floor_mm"],
            "noise_mm": v["noise_mm"],
            "stroke_mm": v["stroke_mm"],
        },
        "folds": [f.name for f in an.folds],
        "sessions": [
            {
                "name": s.name, "path": s.path, "kind": s.kind, "samples": len(s.t),
                "complete_cycles": s.n_complete, "load_kg": s.load_kg, "stress_MPa": s.stress_mpa,
                "wire_length_mm": s.length_mm, "wire_diameter_mm": s.diameter_mm,
                "resistance": s.resistance_ohm()[1] if s.kind == "current" else None,
                "masked_rows": s.masked_rows, "cut": s.cut,
                "notes": s.notes,
            }
            for s in an.prob.sessions
        ],  # fmt: skip
        "timing_s": an.timing,
    }
    shift = loop_shift(an)
    if shift:
        out["loop_shift_check"] = shift
    return _clean(out)


def _sentence(text: str) -> str:
    return f"{text[:1].upper()}{text[1:]}." if text else ""


def _num(x, fmt: str) -> str:
    return "n/a" if x is None else format(x, fmt)


def value_text(pv: dict) -> str:
    """'value ± uncertainty unit' of a parameter entry (uncertainty n/a: not identified)."""
    return f"{_num(pv.get('value'), '.4g')} ± {_num(pv.get('uncertainty'), '.2g')} " \
        f"{pv.get('unit', '')}".rstrip()  # fmt: skip


def _atomic(path: Path, write) -> None:
    from smabench.sessions import atomic_write  # the one atomic write (respects the umask)

    atomic_write(path, write)


def write_json(path: str | Path, doc: dict) -> None:
    _atomic(Path(path), lambda fh: (json.dump(doc, fh, indent=2), fh.write("\n")))


def write_predictions(path: str | Path, an: Analysis, extended: str | None) -> None:
    """CSV: t_s, position_mm, baseline_mm, extended_mm, heldout (0/1) [, session]."""
    several = len(an.prob.sessions) > 1
    ext = extended or "baseline"

    def write(fh):
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["t_s", "position_mm", "baseline_mm", "extended_mm", "heldout"]
                   + (["session"] if several else []))  # fmt: skip
        for s in an.prob.sessions:
            b = an.preds["baseline"][s.name].position_mm
            e = an.preds[ext][s.name].position_mm
            h = an.heldout[s.name]
            for k in range(len(s.t)):
                row = [repr(float(s.t[k])), f"{s.pos[k]:.6g}", f"{b[k]:.6g}", f"{e[k]:.6g}",
                       int(h[k])]  # fmt: skip
                if several:
                    row.append(s.name)
                w.writerow(row)

    _atomic(Path(path), write)


def write_report(folder: str | Path, an: Analysis, doc: dict) -> Path:
    """Markdown report with PNG plots: residual diagnostics, V/I, before/after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ext = doc.get("extended_model") or "baseline"
    sess = an.prob.sessions
    # 1. residual diagnostics of the baseline (held-out samples highlighted)
    fig, axes = plt.subplots(3, 2, figsize=(11, 10))
    axes = axes.ravel()
    for s in sess:
        pr = an.preds["baseline"][s.name]
        r = s.pos - pr.position_mm
        h = an.heldout[s.name]
        temp = s.temp if s.kind == "thermo" else pr.temp_c
        rate = np.gradient(temp, s.t) if len(s.t) > 2 else np.zeros_like(temp)
        branch = np.sign(np.concatenate(([0.0], np.diff(temp))))
        step = max(1, len(s.t) // 4000)
        sl = slice(None, None, step)
        lab = f"{s.name} ({s.stress_mpa:.0f} MPa)" if s.stress_mpa else s.name
        for ax, x, xl in (
            (axes[0], s.t, "t (s)" if not s.row_time else "sample"),
            (axes[1], temp, "temperature (°C, estimated or measured)"),
            (axes[2], rate, "temperature rate (K/s or K/sample)"),
            (axes[3], branch + 0.1 * np.random.default_rng(0).standard_normal(len(r)), "branch"),
            (axes[4], s.cycle, "cycle"),
        ):
            ax.plot(x[sl], r[sl], ".", ms=1.5, label=lab, alpha=0.6)
            ax.plot(x[sl][h[sl]], r[sl][h[sl]], ".", ms=1.5, color="k", alpha=0.3)
            ax.set_xlabel(xl)
            ax.set_ylabel("measured - baseline (mm)")
        if s.stress_mpa is not None:
            axes[5].boxplot([r[h]] if h.any() else [r], positions=[s.stress_mpa], widths=8)
    axes[3].set_xticks([-1, 0, 1], ["cooling", "rest", "heating"])
    axes[5].set_xlabel("stress (MPa)")
    axes[5].set_ylabel("held-out residual (mm)")
    axes[0].legend(fontsize=7, markerscale=4)
    fig.suptitle("baseline residuals (black: held-out samples)")
    fig.tight_layout()
    fig.savefig(folder / "residuals.png", dpi=90)
    plt.close(fig)
    # 2. V/I against position
    vi = [s for s in sess if s.voltage is not None and s.current is not None]
    if vi:
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for s in vi:
            ok = np.isfinite(s.voltage) & (s.current > 0.2 * np.max(s.current))
            ax.plot(s.pos[ok], s.voltage[ok] / s.current[ok], ".", ms=2, label=s.name)
        ax.set_xlabel("position (mm)")
        ax.set_ylabel("V/I (Ω)")
        ax.legend(fontsize=7)
        ax.set_title("resistance against position (current on)")
        fig.tight_layout()
        fig.savefig(folder / "resistance.png", dpi=90)
        plt.close(fig)
    # 3. before / after on the held-out part
    fig, axes = plt.subplots(len(sess), 2, figsize=(12, 3.2 * len(sess)), squeeze=False)
    for k, s in enumerate(sess):
        h = an.heldout[s.name]
        b = an.preds["baseline"][s.name].position_mm
        e = an.preds[ext][s.name].position_mm
        ax = axes[k, 0]
        ax.plot(s.t, s.pos, "k-", lw=0.8, label="measured")
        ax.plot(s.t, b, "-", lw=0.8, label="baseline")
        ax.plot(s.t, e, "--", lw=0.8, label=f"extended ({ext})")
        if h.any():
            ax.axvspan(s.t[h][0], s.t[h][-1], color="0.9", zorder=0)
        ax.set_ylabel(f"{s.name}\nposition (mm)")
        ax.legend(fontsize=7)
        ax = axes[k, 1]
        ax.plot(s.t[h], (s.pos - b)[h], "-", lw=0.8, label="baseline")
        ax.plot(s.t[h], (s.pos - e)[h], "-", lw=0.8, label=ext)
        ax.set_ylabel("held-out residual (mm)")
        ax.legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("sample" if any(s.row_time for s in sess) else "t (s)")
    fig.tight_layout()
    fig.savefig(folder / "before_after.png", dpi=90)
    plt.close(fig)
    # markdown
    lines = ["# Discrepancy analysis", ""]
    if doc.get("assumed"):
        lines += ["**Assumed (not given; they change the result):** "
                  + "; ".join(doc["assumed"]) + ".", ""]  # fmt: skip
    lines += [
        f"**Cause: `{doc['cause']}`**, runner-up: `{doc['runner_up']}`.  ",
        f"{_sentence(cause_text(doc['cause']))}  ",
        f"{doc['reason']}",
        "",
    ]
    if len(doc.get("causes", [])) > 1:
        lines += ["Several causes, each tested on top of the ones before it:", ""]
        for c in doc["causes"]:
            lines.append(f"- `{c['cause']}` (over {c['over']}): held-out gain "
                         f"{c['incremental_gain']:.1%}, p = {c['p_value']:.2g}")
        lines.append("")
    if doc.get("flags"):
        lines += ["**Flags:**", ""] + [f"- {f}" for f in doc["flags"]] + [""]
    lines += [
        f"Held-out RMSE: baseline {doc['baseline_heldout_rmse_mm']:.4g} mm, extended "
        f"({doc['extended_model']}) {doc['extended_heldout_rmse_mm']:.4g} mm, "
        f"gain = 1 - extended/baseline = {doc['gain']:.1%}.",
        f"Folds: {', '.join(doc['folds'])}; {doc['test']['units']} held-out units; "
        f"noise ≈ {doc['test']['noise_mm']:.3g} mm, stroke ≈ {doc['test']['stroke_mm']:.3g} mm, "
        f"structure floor {doc['test']['floor_mm']:.3g} mm.",
        "",
        "| candidate | held-out RMSE (mm) | gain | p (paired, one-sided) | parameter |",
        "|---|---|---|---|---|",
    ]
    for c, row in doc["candidates"].items():
        (pname, pv), = row["parameter"].items()
        lines.append(f"| {c} | {row['heldout_rmse_mm']:.4g} | {row['gain']:.1%} | "
                     f"{row['p_value']:.2g} | {pname} = {value_text(pv)} |")  # fmt: skip
    if doc["skipped_candidates"]:
        lines += ["", "Not tried: " + "; ".join(f"`{k}` ({v})"
                                                for k, v in doc["skipped_candidates"].items())]
    lines += ["", f"## Fitted parameters ({doc['extended_model']})", "",
              "| parameter | value | uncertainty | unit |", "|---|---|---|---|"]  # fmt: skip
    for k, pv in doc["parameters"].items():
        if "value" not in pv:  # a check, not a parameter (resistance_check)
            continue
        val, unc = pv.get("value"), pv.get("uncertainty")
        lines.append(f"| {k} | {_num(val, '.5g')} | {_num(unc, '.2g')} | {pv.get('unit', '')} |")
    vi = doc["parameters"].get("resistance_check")
    if vi:
        lines += ["", f"V/I against the model's ξ while the current is on: ρ(ξ = 0.5) = "
                  f"{vi['rho_mean_uohm_cm']:.2f} µΩ·cm, austenite − martensite = "
                  f"{vi['difference_uohm_cm']:.2f} ± {vi['difference_uncertainty_uohm_cm']:.2g} "
                  f"µΩ·cm ({vi['samples']} samples)."]  # fmt: skip
    if "loop_shift_check" in doc:
        ls = doc["loop_shift_check"]
        lines += ["", f"## Check: mid-stroke temperatures per load ({ls['temperature']})", "",
                  "| stress (MPa) | heating mid (°C) | cooling mid (°C) |", "|---|---|---|"]
        for p in ls["per_session"]:
            lines.append(f"| {p['stress_MPa']:.1f} | {p['mid_heating_C']:.2f} | "
                         f"{p['mid_cooling_C']:.2f} |")  # fmt: skip
        rate = ls.get("stress_rate_mpa_per_k")
        lines.append(f"\nShift of the loops: {ls['shift_k_per_mpa']:.4f} K/MPa → "
                     f"{rate:.2f} MPa/K." if rate else "")  # fmt: skip
    lines += ["", "## Plots", "", "![baseline residuals](residuals.png)", "",
              "![before and after](before_after.png)"]
    if vi:
        lines += ["", "![resistance against position](resistance.png)"]
    lines += ["", "## Sessions", ""]
    for s in doc["sessions"]:
        lines.append(f"- `{s['path']}`: {s['kind']}, {s['samples']} samples, "
                     f"{s['complete_cycles']} complete cycle(s), stress {s['stress_MPa']} MPa, "
                     f"{s['masked_rows']} row(s) masked"
                     + (f"; {'; '.join(s['notes'])}" if s["notes"] else ""))  # fmt: skip
    lines += ["", f"Timing: {doc['timing_s'].get('total', 0):.1f} s in total.", ""]
    md = folder / "report.md"
    md.write_text("\n".join(lines), encoding="utf-8")
    return md
