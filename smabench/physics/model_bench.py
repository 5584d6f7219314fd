"""Benchmark of the loop models on measured loops: accuracy and speed side by side.

For each loop and model: fit errors (``nrmse_percent``, ``ard_percent``), fit time, vectorised
evaluations per second on a 1e6-sample array, and the online step time (µs per sample) along a
sequence with complete, incomplete and inner cycles. Timings are the best of ``repeat`` runs
(time.perf_counter), since these machines are noisy.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from smabench.physics.identify import MODELS, fit_loop
from smabench.physics.loop_models import branch_directions

log = logging.getLogger(__name__)


def excitation_c(t_lo: float, t_hi: float, n: int) -> np.ndarray:
    """A temperature sequence (°C) with complete, incomplete and inner cycles, n samples."""
    s = np.linspace(0.0, 1.0, n)
    span = t_hi - t_lo
    # a slow triangle between the limits plus a faster, smaller one: many reversals
    tri = 1.0 - np.abs(((s * 6.0) % 2.0) - 1.0)
    inner = 0.25 * (1.0 - np.abs(((s * 60.0) % 2.0) - 1.0))
    return t_lo + span * np.clip(0.8 * tri + inner, 0.0, 1.0)


def _best_time(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def benchmark_fit(name: str, temperature_c, position_mm, model: str, *, n_eval=1_000_000,
                  n_step=20_000, repeat=3) -> dict:  # fmt: skip
    """Accuracy and speed of one model on one loop."""
    t0 = time.perf_counter()
    fit = fit_loop(temperature_c, position_mm, model)
    fit_s = time.perf_counter() - t0
    lo, hi = float(np.min(temperature_c)), float(np.max(temperature_c))
    seq = excitation_c(lo, hi, n_eval)
    m = fit.loop_model
    if hasattr(m, "evaluate"):
        heating = branch_directions(seq[:1000], fit.deadband_k)
        heating = np.resize(heating, seq.size)
        m.evaluate(seq[:1000], heating[:1000])
        vec_s = _best_time(lambda: m.evaluate(seq, heating), repeat)
        stepper = fit.stepper()
        step_seq = seq[:: max(1, n_eval // n_step)][:n_step]

        def run_steps():
            stepper.reset()
            step = stepper.step
            for t in step_seq:
                step(t)

        step_s = _best_time(run_steps, repeat) / step_seq.size
    else:  # the operator model: history is its nature, predict() runs the sequence
        n_vec = min(n_eval, 200_000)
        vec_s = _best_time(lambda: m.predict(seq[:n_vec]), repeat) * n_eval / n_vec
        from smabench.physics.preisach import PreisachStepper

        stepper = PreisachStepper(m)
        step_seq = seq[:: max(1, n_eval // n_step)][:n_step]

        def run_steps():
            stepper.reset()
            step = stepper.step
            for t in step_seq:
                step(t)

        step_s = _best_time(run_steps, repeat) / step_seq.size
    return {
        "loop": name,
        "model": model,
        "nrmse_percent": fit.nrmse_percent,
        "ard_percent": fit.ard_percent,
        "rmse_mm": fit.rmse_mm,
        "fit_s": fit_s,
        "evals_per_s": n_eval / vec_s,
        "step_us": step_s * 1e6,
    }


def benchmark_models(loops, models=None, **kw) -> list[dict]:
    """Rows for every (loop, model); ``loops`` is a list of (name, temperature_c, position_mm)."""
    rows = []
    for name, t, y in loops:
        for model in models or list(MODELS):
            rows.append(benchmark_fit(name, t, y, model, **kw))
            log.info("%s", rows[-1])
    return rows


def benchmark_preisach_rows(temperature_c, position_mm, n_rows: int = 26_000) -> dict:
    """Preisach fit time, peak traced memory and accuracy on ``n_rows`` samples with many
    reversals: a sigmoid model fitted to the measured loop is stepped along
    :func:`excitation_c` (complete, incomplete and inner cycles) with 0.5 % noise."""
    import tracemalloc

    from smabench.physics.preisach import PreisachModel

    fit = fit_loop(temperature_c, position_mm, "sigmoid")
    seq = excitation_c(float(np.min(temperature_c)), float(np.max(temperature_c)), n_rows)
    y = fit.stepper().run(seq)
    y = y + np.random.default_rng(1).normal(0.0, 0.005 * float(np.ptp(y)), y.size)
    tracemalloc.start()
    t0 = time.perf_counter()
    model = PreisachModel.fit(seq, y)
    fit_s = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    nrmse = 100.0 * float(np.sqrt(np.mean((model.predict(seq) - y) ** 2)) / np.ptp(y))
    return {"rows": n_rows, "fit_s": fit_s, "peak_mb": peak / 2**20, "nrmse_percent": nrmse}


def format_table(rows: list[dict]) -> str:
    """Plain-text table plus the model 1 vs peer speed ratio."""
    head = (
        f"{'loop':24s} {'model':9s} {'nrmse %':>8s} {'ard %':>7s} {'rmse mm':>8s} "
        f"{'fit s':>6s} {'evals/s':>10s} {'step µs':>8s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['loop']:24s} {r['model']:9s} {r['nrmse_percent']:8.3f} {r['ard_percent']:7.3f} "
            f"{r['rmse_mm']:8.4f} {r['fit_s']:6.2f} {r['evals_per_s']:10.3g} {r['step_us']:8.2f}"
        )
    by = {(r["loop"], r["model"]): r for r in rows}
    for loop in dict.fromkeys(r["loop"] for r in rows):
        m1, peer = by.get((loop, "1")), by.get((loop, "preisach"))
        if m1 and peer:
            lines.append(
                f"{loop}: model 1 is {m1['evals_per_s'] / peer['evals_per_s']:.0f}× faster "
                f"vectorised and {peer['step_us'] / m1['step_us']:.1f}× faster per online step "
                f"than the Preisach peer; nrmse {m1['nrmse_percent']:.2f} % vs "
                f"{peer['nrmse_percent']:.2f} %"
            )
    return "\n".join(lines)
