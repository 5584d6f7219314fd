"""Report PNGs of ``smabench characterize --report DIR`` (matplotlib, Agg, written atomically).

- ``evolution.png``: As/Af/Ms/Mf, actuation and residual strains, hysteresis over the cycles;
- ``tangents-<session>-cycle<k>.png``: the tangent construction on chosen cycles (first, middle,
  last), both branches with their three lines and the intersections;
- ``phase_diagram.png``: transformation temperatures against stress with the fitted slopes.
Every figure says whether the temperature was measured or estimated.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from smabench.characterize.e3097 import TEMPERATURE_KEYS, BranchResult
from smabench.sessions import atomic_write

log = logging.getLogger(__name__)

COLORS = {"As": "tab:red", "Af": "tab:orange", "Ms": "tab:blue", "Mf": "tab:cyan"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _pyplot()
    try:
        atomic_write(path, lambda fh: fig.savefig(fh, format="png"), binary=True)
    finally:
        plt.close(fig)
    return path


def _label(s: dict[str, Any]) -> str:
    load = s.get("load_MPa")
    name = Path(s["session"]).name
    return f"{name} ({load:.0f} MPa)" if load is not None else name


def _vals(cycles: list[dict], key: str) -> np.ndarray:
    return np.array([np.nan if c.get(key) is None else c[key] for c in cycles], dtype=float)


def evolution_png(doc: dict[str, Any], path: Path) -> Path:
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), dpi=100, sharex=True)
    for s in doc["sessions"]:
        cyc = s["cycles"]
        k = np.array([c["cycle"] for c in cyc])
        tag = f"{_label(s)}, {s['temperature_source']}"
        for key in TEMPERATURE_KEYS:
            axes[0].plot(k, _vals(cyc, f"{key}_C"), ".-", ms=3, lw=0.8, color=COLORS[key],
                         label=f"{key} {tag}" if len(doc["sessions"]) < 4 else key)  # fmt: skip
        axes[1].plot(k, _vals(cyc, "actuation_strain") * 100, ".-", ms=3, lw=0.8,
                     label=f"actuation {tag}")  # fmt: skip
        axes[1].plot(k, _vals(cyc, "accumulated_residual_strain") * 100, ".--", ms=3, lw=0.8,
                     label=f"accumulated residual {tag}")  # fmt: skip
        axes[2].plot(k, _vals(cyc, "hysteresis_K"), ".-", ms=3, lw=0.8, label=tag)
    axes[0].set_ylabel("temperature (°C)")
    axes[1].set_ylabel("strain (%)")
    axes[2].set_ylabel("hysteresis at mid-transformation (K)")
    axes[2].set_xlabel("cycle")
    for ax in axes:
        ax.grid(alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        uniq = dict(zip(labels, handles, strict=True))
        ax.legend(uniq.values(), uniq.keys(), fontsize=7, loc="best")
    axes[0].set_title("ASTM E3097 properties over the cycles")
    fig.tight_layout()
    return _save(fig, path)


def tangent_png(session: dict[str, Any], k: int, branches: tuple[BranchResult, BranchResult],
                path: Path) -> Path:  # fmt: skip
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5), dpi=100)
    cyc = next(c for c in session["cycles"] if c["cycle"] == k)
    for br, color in zip(branches, ("tab:red", "tab:blue"), strict=True):
        ax.plot(br.t_c, br.strain * 100, ".", ms=3, color=color, alpha=0.6, label=br.kind)
        t = np.linspace(br.t_c.min(), br.t_c.max(), 50)
        for line, style in ((br.martensite, ":"), (br.austenite, "--")):
            if line is not None:
                ax.plot(t, line(t) * 100, style, color=color, lw=1)
        if br.transformation is not None:
            e = np.linspace(br.strain.min(), br.strain.max(), 20)
            ax.plot(br.transformation(e), e * 100, "-", color=color, lw=1)
    for key in TEMPERATURE_KEYS:
        T, e = cyc.get(f"{key}_C"), cyc.get(f"{key}_strain")
        if T is not None and e is not None:
            ax.plot([T], [e * 100], "o", color=COLORS[key], ms=7, mfc="none", mew=1.5)
            ax.annotate(f"{key} {T:.1f} °C", (T, e * 100), textcoords="offset points",
                        xytext=(6, 4), fontsize=8)  # fmt: skip
    src = session["temperature_source"]
    ax.set_xlabel(f"temperature (°C, {src})")
    ax.set_ylabel("strain (%)")
    ax.set_title(f"tangent construction, {_label(session)}, cycle {k}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def phase_png(doc: dict[str, Any], path: Path) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5), dpi=100)
    pd = doc.get("phase_diagram") or {}
    sources = {s["temperature_source"] for s in doc["sessions"]}
    for key in TEMPERATURE_KEYS:
        sig, temp = [], []
        for s in doc["sessions"]:
            if s.get("load_MPa") is None:
                continue
            v = _vals(s["cycles"], f"{key}_C")
            sig += [s["load_MPa"]] * int(np.isfinite(v).sum())
            temp += v[np.isfinite(v)].tolist()
        ax.plot(temp, sig, "o", ms=3, color=COLORS[key], alpha=0.6)
        fit = pd.get(key) or {}
        slope = fit.get("slope_MPa_per_K")
        if slope and fit.get("T_at_0MPa_C") is not None and sig:
            s_line = np.linspace(min(sig), max(sig), 10)
            t_line = fit["T_at_0MPa_C"] + s_line / slope
            unc = fit.get("uncertainty")
            ax.plot(t_line, s_line, "-", color=COLORS[key],
                    label=f"{key}: {slope:.2f} ± {unc:.2f} MPa/K" if unc is not None
                    else f"{key}: {slope:.2f} MPa/K")  # fmt: skip
    ax.set_xlabel(f"temperature (°C, {'/'.join(sorted(sources))})")
    ax.set_ylabel("stress (MPa)")
    ax.set_title("stress–temperature phase diagram (Clausius–Clapeyron slopes)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def chosen_cycles(n: int) -> list[int]:
    """Cycles whose tangent construction is drawn: first, middle, last."""
    return sorted({1, max(1, (n + 1) // 2), max(1, n)})


def write_report(doc: dict[str, Any], folder: str | Path) -> list[Path]:
    """All PNGs into ``folder``; returns their paths."""
    folder = Path(folder)
    out = [evolution_png(doc, folder / "evolution.png")]
    for i, s in enumerate(doc["sessions"]):
        for k, br in sorted((s.get("_branches") or {}).items()):
            name = f"tangents-{i + 1:02d}-{Path(s['session']).name}-cycle{k}.png"
            out.append(tangent_png(s, k, br, folder / name))
    if doc.get("phase_diagram"):
        out.append(phase_png(doc, folder / "phase_diagram.png"))
    return out
