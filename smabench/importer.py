"""Import measured loops from plain text (whitespace- or comma-separated) into a session folder.

Column names come from the session contract plus ``strain`` (dimensionless; × wire length gives
``position_mm``), ``stress_MPa`` and ``temperature_C``; ``skip`` ignores a column.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from smabench.sessions import COLUMNS, EXTRA_COLUMNS, TEXT_COLUMNS, write_session

log = logging.getLogger(__name__)

IMPORT_COLUMNS = frozenset(COLUMNS) - TEXT_COLUMNS | set(EXTRA_COLUMNS) | {"strain", "skip"}
_SPLIT = re.compile(r"[,;\s]+")


class TextImportError(ValueError):
    """Input text that cannot be imported (message names the line and the problem)."""


def parse_columns(spec: str) -> list[str]:
    """Parse ``"temperature_C,strain,stress_MPa"`` and check every name is known."""
    names = [c.strip() for c in spec.split(",") if c.strip()]
    if not names:
        raise TextImportError("--columns is empty")
    unknown = [c for c in names if c not in IMPORT_COLUMNS]
    if unknown:
        known = ", ".join(sorted(IMPORT_COLUMNS))
        raise TextImportError(f"unknown column name(s) {', '.join(unknown)}; known: {known}")
    dup = {c for c in names if names.count(c) > 1 and c != "skip"}
    if dup:
        raise TextImportError(f"column name(s) given twice: {', '.join(sorted(dup))}")
    if "position_mm" not in names and "strain" not in names:
        raise TextImportError("--columns needs position_mm or strain")
    if "temperature_C" not in names and "current_A" not in names:
        raise TextImportError("--columns needs temperature_C or current_A")
    return names


def read_table(path: str | Path, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Read numeric rows with ``len(names)`` fields; a non-numeric first line is a header."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise TextImportError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise TextImportError(f"{path}: not a text file") from None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f for f in _SPLIT.split(stripped) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not rows and lineno == _first_data_line(text):
                log.info("%s: line %d taken as a header: %s", path, lineno, stripped)
                continue
            raise TextImportError(f"{path}: line {lineno}: not a number in {stripped!r}") from None
        if len(values) != len(names):
            raise TextImportError(
                f"{path}: line {lineno} has {len(values)} columns, --columns names {len(names)}"
            )
        if not all(np.isfinite(values)):
            raise TextImportError(f"{path}: line {lineno}: NaN or infinite value in {stripped!r}")
        rows.append(values)
    if len(rows) < 2:
        raise TextImportError(f"{path}: fewer than 2 data rows")
    table = np.asarray(rows, dtype=float)
    return {n: table[:, i] for i, n in enumerate(names) if n != "skip"}


def _first_data_line(text: str) -> int:
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            return lineno
    return 0


def import_text(
    path: str | Path,
    columns: str,
    out: str | Path,
    wire_length_mm: float | None = None,
    load_kg: float | None = None,
    wire_diameter_mm: float | None = None,
) -> Path:
    """Import ``path`` into a new session folder ``out``; returns the folder."""
    names = parse_columns(columns)
    if wire_length_mm is not None and not (0 < wire_length_mm < 1e5):
        raise TextImportError(f"--wire-length-mm must be positive, got {wire_length_mm}")
    if "strain" in names and wire_length_mm is None:
        raise TextImportError("a strain column needs --wire-length-mm to give position_mm")
    data = read_table(path, names)
    if "strain" in data:
        data["position_mm"] = data.pop("strain") * float(wire_length_mm)
    n = len(data["position_mm"])
    meta: dict = {
        "kind": "thermometer_loop" if "temperature_C" in data else "current_driven",
        "source": str(Path(path).name),
        "imported_columns": names,
        "wire": {"length_mm": wire_length_mm, "diameter_mm": wire_diameter_mm},
        "load_kg": load_kg,
        "status": "completed",
        "end_reason": "imported",
    }
    if "stress_MPa" in data:
        meta["stress_MPa_mean"] = round(float(np.mean(data["stress_MPa"])), 3)
    if "t_s" not in data:
        data["t_s"] = np.arange(n, dtype=float)
        meta["t_s_is_row_index"] = True
    return write_session(out, meta, data)
