"""PNG plots of loops for the CLI and reports (matplotlib, headless Agg backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_loop_png(
    path: str | Path,
    temperature_c: np.ndarray,
    position_mm: np.ndarray,
    models: Sequence[tuple[str, np.ndarray]] = (),
    title: str = "",
    xlabel: str = "temperature (°C)",
) -> Path:
    """Measured loop (dots) with model curves over it; written atomically."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    ax.plot(temperature_c, position_mm, ".", ms=2.5, color="0.45", label="measured")
    styles = ["-", "--", "-.", ":"]
    for i, (name, pred) in enumerate(models):
        ax.plot(temperature_c, pred, styles[i % len(styles)], lw=1.3, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("position (mm)")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    from smabench.sessions import atomic_write

    path = Path(path)
    try:
        atomic_write(path, lambda fh: fig.savefig(fh, format="png"), binary=True)
    finally:
        plt.close(fig)
    return path
