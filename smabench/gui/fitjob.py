"""Fitting a recorded session's loop: the job the GUI's computation process runs
(:mod:`smabench.gui.worker`), so nothing here imports Qt. Cycles are shown counting from 1 (the
recorded ``cycle`` column counts from 0)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np


def shown_cycle(index: float) -> int:
    """The cycle number the operator sees for a recorded ``cycle`` index (0 → 1)."""
    return int(index) + 1


def replay_columns(session) -> dict[str, np.ndarray]:
    """A loaded session's columns as the plots want them."""
    n = len(session)
    cols = {c: session.data[c] for c in session.data if c != "mode"}
    if "t_s" not in cols:
        cols["t_s"] = np.arange(n, dtype=float)
    cols.setdefault("cycle", np.zeros(n))
    return cols


def fit_session(folder: Path, model: str, cycle: int | None) -> dict[str, Any]:
    """Load ``folder`` and fit ``model`` to cycle ``cycle`` (counted from 1; None: the last
    complete one); runs off the GUI thread. ValueError in words when it cannot."""
    from smabench.physics.identify import FitError, fit_loop
    from smabench.sessions import load_session

    t0 = time.perf_counter()
    s = load_session(folder)
    cols = replay_columns(s)
    idx = np.asarray(cols["cycle"], dtype=float)
    finite = idx[np.isfinite(idx)]
    if cycle is None:
        chosen = float(finite.max()) if finite.size else 0.0
    else:
        chosen = float(cycle - 1)
        if finite.size and chosen not in set(finite.tolist()):
            raise ValueError(f"this session has cycles 1 to {shown_cycle(finite.max())}, "
                             f"not {cycle}")  # fmt: skip
    sel = idx == chosen if finite.size else np.ones(idx.size, bool)
    # the temperature the loop plot shows: measured when the session has it, else estimated
    measured = np.asarray(cols.get("temperature_C", np.full(idx.size, np.nan)), float)
    use_measured = bool(np.isfinite(measured).any())
    source = "measured" if use_measured else "estimated"
    temp = measured[sel] if use_measured else np.asarray(cols["temperature_est_C"], float)[sel]
    pos = np.asarray(cols["position_mm"], float)[sel]
    ok = np.isfinite(temp) & np.isfinite(pos)
    try:
        fit = fit_loop(temp[ok], pos[ok], model)
    except FitError as exc:
        raise ValueError(f"the {model} model could not be fitted to cycle "
                         f"{shown_cycle(chosen)}: {exc}") from None  # fmt: skip
    lines = [f"{Path(folder).name}: model {fit.model} on cycle {shown_cycle(chosen)} "
             f"({fit.n_points} points, {source} temperature, "
             f"{time.perf_counter() - t0:.1f} s)",
             f"rmse {fit.rmse_mm:.4f} mm   nrmse {fit.nrmse_percent:.3f} % of stroke   "
             f"ard {fit.ard_percent:.3f} %"]  # fmt: skip
    lines += [f"  {k} = {v:.6g}" for k, v in fit.parameters.items()]
    return {"text": "\n".join(lines), "temp": temp[ok], "model_mm": fit.predict(temp[ok]),
            "nrmse_percent": fit.nrmse_percent, "rmse_mm": fit.rmse_mm,
            "cycle": shown_cycle(chosen), "folder": str(folder)}  # fmt: skip
