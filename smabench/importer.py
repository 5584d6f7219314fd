"""Import measured loops from the text files labs and testing machines write into a session.

Real exports are not tidy tables. :func:`sniff_layout` finds, before any number is converted:

- metadata lines above the table (``Test : Start of hold value,"100.00000",MPa``) and blank lines;
- a header line of column names and a units line below it (``(s),(mm),(N)``);
- the separator: tab, semicolon, comma or white space, whichever splits the data lines into the
  same number of fields;
- quoted numbers (``"0.00000"``) and decimal commas (``29,5`` with tab, semicolon or white-space
  separators; with comma separators only ``--decimal ,`` can say so).

``--preview`` prints what it found (:meth:`Layout.describe`) and the first rows, so the
``--columns`` line can be written from it. Column names come from the session contract plus
``strain`` (dimensionless; × wire length gives ``position_mm``), ``stress_MPa``,
``temperature_C`` and ``skip``. A loop needs a position (``position_mm`` or ``strain``) and what
drove it: a measured temperature (``temperature_C``), the current (``current_A``) or the voltage
(``voltage_V``, optionally with ``current_A``: a heat balance then stands in for the temperature).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from smabench.sessions import COLUMNS, EXTRA_COLUMNS, TEXT_COLUMNS, write_session

log = logging.getLogger(__name__)

IMPORT_COLUMNS = frozenset(COLUMNS) - TEXT_COLUMNS | set(EXTRA_COLUMNS) | {"strain", "skip"}
DRIVERS = ("temperature_C", "current_A", "voltage_V")
"""What a loop was driven by: one of these columns is needed."""
SEPARATORS = {"tab": "\t", "semicolon": ";", "comma": ",", "whitespace": None}
SNIFF_ROWS = 500
"""Rows that decide the layout; every row is still checked when the table is read."""
SNIFF_LINES = 2000
"""Lines from the top searched for the table (metadata above it included)."""
_NUMBER = re.compile(r"^[+-]?((\d+([.,]\d*)?|[.,]\d+)([eE][+-]?\d+)?|nan|inf(inity)?)$", re.I)
"""A number as exports write them (nan/inf count, so the reader can name their line)."""
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")
_UNITS = re.compile(r"^\(?\s*[^\d\s()]*[^()]*\)?$")


class TextImportError(ValueError):
    """Input text that cannot be imported (message names the line and the problem)."""


@dataclass
class Layout:
    """Where the table is in a text file (1-based line numbers)."""

    separator: str  # a key of SEPARATORS
    decimal: str  # "." or ","
    first_data_line: int
    n_fields: int
    header: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    metadata: list[str] = field(default_factory=list)
    quoted: bool = False
    rows: int = 0  # data rows read (read_table)
    empty_cells: dict[str, int] = field(default_factory=dict)  # column -> cells kept as NaN

    def describe(self) -> str:
        """The layout in words, one fact a line (``smabench import --preview``)."""
        lines = [
            f"separator: {self.separator}; decimal mark: {self.decimal!r}"
            + ("; numbers quoted" if self.quoted else ""),
            f"table: {self.n_fields} columns, data from line {self.first_data_line}",
        ]
        if self.metadata:
            lines.append("metadata lines: " + " | ".join(self.metadata))
        if self.header:
            names = [
                f"{k + 1}: {h}" + (f" {self.units[k]}" if k < len(self.units) else "")
                for k, h in enumerate(self.header)
            ]
            lines.append("columns: " + "; ".join(names))
        return "\n".join(lines)


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
    if not any(d in names for d in DRIVERS):
        raise TextImportError("--columns needs temperature_C, current_A or voltage_V")
    return names


def _split(line: str, separator: str) -> list[str]:
    sep = SEPARATORS[separator]
    if sep is None:
        return line.split()
    return [f.strip() for f in next(csv.reader(io.StringIO(line), delimiter=sep))]


def _unquote(field: str) -> str:
    f = field.strip()
    if len(f) >= 2 and f[0] == f[-1] and f[0] in "\"'":
        return f[1:-1].strip()
    return f


def _numeric(fields: list[str]) -> bool:
    return bool(fields) and all(_NUMBER.match(_unquote(f)) for f in fields)


def _data_line(fields: list[str]) -> bool:
    """A line of the table: every cell a number or empty, at least one number."""
    cells = [_unquote(f) for f in fields]
    return any(cells) and all(not c or _NUMBER.match(c) for c in cells)


def _first_block(lines: list[str], name: str) -> tuple[int, int, int] | None:
    """(rows, first line index, fields) of the table for separator ``name``.

    The longest block of data lines with one field count decides the table's width; the table
    starts at the first block of that width (a row above a bad cell is a row, never metadata),
    and a line of numbers of another width above it is metadata."""
    blocks: list[tuple[int, int, int]] = []
    k = 0
    while k < len(lines):
        fields = _split(lines[k], name) if lines[k].strip() else []
        if not fields or not _data_line(fields):
            k += 1
            continue
        start, n_fields, rows = k, len(fields), 0
        while k < len(lines) and rows < SNIFF_ROWS:
            s = lines[k].strip()
            if not s or s.startswith("#"):
                k += 1
                continue
            f = _split(lines[k], name)
            if len(f) != n_fields or not _data_line(f):
                break
            rows += 1
            k += 1
        blocks.append((rows, start, n_fields))
        if rows >= SNIFF_ROWS:
            break
        k = max(k, start + 1)
    if not blocks:
        return None
    rows, _, n_fields = max(blocks, key=lambda b: (b[0], b[2]))
    start = next(b[1] for b in blocks if b[2] == n_fields)
    return rows, start, n_fields


def sniff_layout(text: str, decimal: str | None = None) -> Layout:
    """Find the table in ``text`` (TextImportError when there is none).

    The table starts at the first block of data lines (numbers or empty cells); only the lines
    above it can be metadata, a header or units, so no data row is ever taken for metadata."""
    lines = text.splitlines()[:SNIFF_LINES]
    best: tuple[int, str, int, int] | None = None  # (rows, separator, first line index, fields)
    for name in SEPARATORS:
        found = _first_block(lines, name)
        if found is None:
            continue
        rows, start, n_fields = found
        # prefer the separator giving the longest run, then more fields
        if best is None or (rows, n_fields) > (best[0], best[3]):
            best = (rows, name, start, n_fields)
    if best is None:
        raise TextImportError("no table: no line of numbers found")
    _, separator, start, n_fields = best
    quoted = '"' in lines[start] or "'" in lines[start]
    if decimal is None:
        sample = [f for k in range(start, min(start + 50, len(lines)))
                  for f in (_unquote(x) for x in _split(lines[k], separator)) if f]  # fmt: skip
        has_comma = any(_DECIMAL_COMMA.match(f) for f in sample)
        decimal = "," if has_comma and separator != "comma" else "."
    elif decimal not in (".", ","):
        raise TextImportError(f"--decimal must be '.' or ',', got {decimal!r}")
    # above the table: units line, header line, metadata (blank lines skipped)
    above = [(k, lines[k]) for k in range(start) if lines[k].strip()]
    header: list[str] = []
    units: list[str] = []
    if above:
        k, line = above[-1]
        fields = [_unquote(f) for f in _split(line, separator)]
        if len(fields) == n_fields and all(_UNITS.match(f) and ("(" in f or "[" in f or not f)
                                           for f in fields):  # fmt: skip
            units = fields
            above.pop()
    if above:
        k, line = above[-1]
        fields = [_unquote(f) for f in _split(line, separator)]
        if len(fields) == n_fields and not _numeric(fields):
            header = fields
            above.pop()
    metadata = [line.strip() for _, line in above if not line.strip().startswith("#")]
    return Layout(separator, decimal, start + 1, n_fields, header, units, metadata, quoted)


HEAD_BYTES = 1 << 20
"""The first bytes of a file that decide its layout (a large file is never read whole)."""
PROGRESS_S = 1.0
"""Seconds between two progress reports of a large import."""
PROGRESS_MIN_BYTES = 16 << 20
"""Files from this size on report their progress."""
WRITE_PROGRESS_MIN_ROWS = 500_000
"""Imports from this many rows on report the progress of writing the session."""
ProgressFn = Callable[[int, int, int], None]
"""``progress(rows, bytes_read, bytes_total)``, called at most every :data:`PROGRESS_S`."""


def _decode(raw: bytes, path: Path) -> tuple[str, str]:
    if b"\0" in raw[:4096]:
        raise TextImportError(f"{path}: not a text file")
    for encoding in ("utf-8-sig", "cp1252"):  # Windows exports are often cp1252
        try:
            return raw.decode(encoding), encoding
        except UnicodeDecodeError:
            continue
    raise TextImportError(f"{path}: not a text file")  # pragma: no cover (cp1252 takes all)


def read_text(path: str | Path) -> str:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise TextImportError(f"cannot read {path}: {exc.strerror}") from None
    return _decode(raw, path)[0]


def _read_head(path: Path) -> tuple[bytes, bool]:
    """The first :data:`HEAD_BYTES` of ``path`` cut at a line end; (bytes, whole file?)."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read(HEAD_BYTES + 1)
    except OSError as exc:
        raise TextImportError(f"cannot read {path}: {exc.strerror}") from None
    if len(raw) <= HEAD_BYTES:
        return raw, True
    cut = raw.rfind(b"\n")
    return (raw[: cut + 1] if cut > 0 else raw), False


def _check_names(path: Path, names: Sequence[str], layout: Layout) -> None:
    if len(names) != layout.n_fields:
        raise TextImportError(
            f"{path}: the table has {layout.n_fields} columns"
            + (f" ({', '.join(layout.header)})" if layout.header else "")
            + f", --columns names {len(names)}"
        )


def _read_lines(
    path: Path, text: str, names: Sequence[str], layout: Layout
) -> dict[str, np.ndarray]:
    """Every line from the table's first on, one at a time (names the line of any problem)."""
    keep = [i for i, n in enumerate(names) if n != "skip"]
    rows: list[list[float]] = []
    lines = text.splitlines()
    for lineno in range(layout.first_data_line, len(lines) + 1):
        stripped = lines[lineno - 1].strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [_unquote(f) for f in _split(lines[lineno - 1], layout.separator)]
        if len(fields) != layout.n_fields:
            raise TextImportError(
                f"{path}: line {lineno} has {len(fields)} columns, the table {layout.n_fields}"
            )
        if layout.decimal == ",":
            fields = [f.replace(",", ".") for f in fields]
        try:
            values = [float(fields[i]) if fields[i] else math.nan for i in keep]
        except ValueError:
            raise TextImportError(f"{path}: line {lineno}: not a number in {stripped!r}") from None
        if any(fields[i] and not math.isfinite(v) for i, v in zip(keep, values, strict=True)):
            raise TextImportError(f"{path}: line {lineno}: NaN or infinite value in {stripped!r}")
        rows.append(values)
    table = np.asarray(rows, dtype=float).reshape(len(rows), len(keep))
    return {names[i]: table[:, k] for k, i in enumerate(keep)}


def _read_arrow(
    path: Path, head: bytes, names: Sequence[str], layout: Layout, encoding: str,
    progress: ProgressFn | None,
) -> dict[str, np.ndarray] | None:  # fmt: skip
    """The table through pyarrow's streaming CSV reader (≈ 50× the line reader, memory of the
    columns only); None when the file needs the line reader (white-space separated, comment
    lines, ragged or bad cells, infinities: it names the line)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    if layout.separator == "whitespace":
        return None
    offset = 0
    for _ in range(layout.first_data_line - 1):
        offset = head.find(b"\n", offset) + 1
        if offset == 0:
            return None
    if head[:offset].decode(encoding, "replace").count("\n") != len(
        head[:offset].decode(encoding, "replace").splitlines()
    ):
        return None  # line ends other than \n above the table: the line reader
    cols = [f"c{i}" for i in range(layout.n_fields)]
    want = {cols[i]: n for i, n in enumerate(names) if n != "skip"}
    size = path.stat().st_size
    source = open(path, "rb")  # noqa: SIM115 - closed below
    source.seek(offset)
    chunks: dict[str, list[np.ndarray]] = {n: [] for n in want.values()}
    rows = empty = 0
    try:
        reader = pacsv.open_csv(
            source,
            read_options=pacsv.ReadOptions(
                column_names=cols, block_size=8 << 20,
                encoding="utf8" if encoding == "utf-8-sig" else encoding,
            ),
            parse_options=pacsv.ParseOptions(delimiter=SEPARATORS[layout.separator],
                                             ignore_empty_lines=True),
            convert_options=pacsv.ConvertOptions(
                column_types={c: pa.float64() for c in want}, include_columns=list(want),
                null_values=[""], strings_can_be_null=True,
                decimal_point=layout.decimal,
            ),
        )  # fmt: skip
        last = time.monotonic()
        table_lines = max(1, head.count(b"\n", offset))
        row_bytes = (len(head) - offset) / table_lines  # for the progress estimate
        if size < PROGRESS_MIN_BYTES:
            progress = None
        for batch in reader:
            for c, n in want.items():
                col = batch.column(c)
                empty += col.null_count
                chunks[n].append(col.to_numpy(zero_copy_only=False))
            rows += batch.num_rows
            if progress is not None and time.monotonic() - last >= PROGRESS_S:
                progress(rows, min(size, int(offset + rows * row_bytes)), size)
                last = time.monotonic()
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, UnicodeDecodeError):
        return None
    finally:
        source.close()
    data = {n: np.concatenate(c) if c else np.zeros(0) for n, c in chunks.items()}
    if sum(int(np.count_nonzero(~np.isfinite(v))) for v in data.values()) != empty:
        return None  # a written nan or inf: the line reader names its line
    if progress is not None:
        progress(rows, size, size)
    return data


def read_table(
    path: str | Path, names: Sequence[str], decimal: str | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, np.ndarray], Layout]:  # fmt: skip
    """Read the table of ``path`` into named columns; returns (columns, layout).

    Every line from the table's first on is a data row: an empty cell is kept as NaN and
    counted in ``layout.empty_cells``; a cell that is not a number, a written NaN or infinity or
    a line with another number of cells is an error naming the line. A large file streams (pyarrow's
    CSV reader, ``progress`` called about once a second) and is never held as text."""
    path = Path(path)
    head, whole = _read_head(path)
    head_text, encoding = _decode(head, path)
    layout = sniff_layout(head_text, decimal)
    _check_names(path, names, layout)
    data = _read_arrow(path, head, names, layout, encoding, progress)
    if data is None:
        text = head_text if whole else read_text(path)
        data = _read_lines(path, text, names, layout)
    n = len(next(iter(data.values()))) if data else 0
    if n < 2:
        raise TextImportError(f"{path}: fewer than 2 data rows")
    layout.rows = n
    layout.empty_cells = {k: int(np.isnan(v).sum()) for k, v in data.items()
                          if np.isnan(v).any()}  # fmt: skip
    return data, layout


def preview(path: str | Path, decimal: str | None = None, rows: int = 5) -> str:
    """The layout found in ``path`` and its first rows (``smabench import --preview``)."""
    text = read_text(path)
    layout = sniff_layout(text, decimal)
    lines = text.splitlines()
    first = [lines[k].strip() for k in range(layout.first_data_line - 1, len(lines))
             if lines[k].strip()][:rows]  # fmt: skip
    return layout.describe() + "\nfirst rows:\n" + "\n".join("  " + r for r in first)


def import_text(
    path: str | Path,
    columns: str,
    out: str | Path,
    wire_length_mm: float | None = None,
    load_kg: float | None = None,
    wire_diameter_mm: float | None = None,
    decimal: str | None = None,
    progress: ProgressFn | None = None,
    write_progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Import ``path`` into a new session folder ``out``; returns the folder. Its
    ``session.json`` says how many rows were read and how many cells were empty (kept as NaN)
    under ``import``. ``progress``: the reading (:data:`ProgressFn`); ``write_progress(rows_done,
    rows)``: the writing of the session, both about once a second on a large file."""
    names = parse_columns(columns)
    if wire_length_mm is not None and not (0 < wire_length_mm < 1e5):
        raise TextImportError(f"--wire-length-mm must be positive, got {wire_length_mm}")
    if "strain" in names and wire_length_mm is None:
        raise TextImportError("a strain column needs --wire-length-mm to give position_mm")
    data, layout = read_table(path, names, decimal, progress)
    if "strain" in data:
        data["position_mm"] = data.pop("strain") * float(wire_length_mm)
    n = len(data["position_mm"])
    if "temperature_C" in data:
        kind = "thermometer_loop"
    elif "current_A" in data:
        kind = "current_driven"
    else:
        kind = "voltage_driven"
    meta: dict = {
        "kind": kind,
        "source": str(Path(path).name),
        "imported_columns": names,
        "source_layout": {
            "separator": layout.separator,
            "decimal": layout.decimal,
            "header": layout.header,
            "units": layout.units,
            "metadata": layout.metadata,
        },
        "import": {"rows": layout.rows, "empty_cells": layout.empty_cells},
        "wire": {"length_mm": wire_length_mm, "diameter_mm": wire_diameter_mm},
        "load_kg": load_kg,
        "status": "completed",
        "end_reason": "imported",
    }
    if "stress_MPa" in data:
        meta["stress_MPa_mean"] = round(float(np.nanmean(data["stress_MPa"])), 3)
    if "t_s" not in data:
        data["t_s"] = np.arange(n, dtype=float)
        meta["t_s_is_row_index"] = True
    if n < WRITE_PROGRESS_MIN_ROWS:
        write_progress = None
    return write_session(out, meta, data, progress=write_progress)
