"""A compiled reader for the numeric columns of plain CSV text (numba; ≈ 10× numpy's parser).

Used by :mod:`smabench.sessions` for samples files: comma-separated, no quotes, one header line
already removed. Empty cells and ``nan`` read as NaN. Every number is read exactly as ``float()``
reads it: a mantissa up to 2**53 with a decimal exponent within ±22 is one correctly rounded
operation here (Clinger's fast path); the others (17 significant digits, subnormals, large
exponents) are noted and converted afterwards by pyarrow's correctly rounded parser.
A cell that is not a number in a requested column, or a line with the wrong number of cells,
makes :func:`parse_numeric` return ``None`` so the caller can use a reader that names the line.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _parse(buf, ncols, slot, nwant, out):  # pragma: no cover - compiled
    """(rows read or -1 - bad row, cells to convert exactly: rows of (row, slot, start, end,
    negative))."""
    fix = np.empty((1024, 5), dtype=np.int64)
    nfix = 0
    n = buf.size
    i = 0
    row = 0
    nrows = out.shape[0]
    pow10 = np.empty(23)
    p = 1.0
    for k in range(23):
        pow10[k] = p
        p *= 10.0
    while i < n and row < nrows:
        col = 0
        while True:
            s = slot[col] if col < ncols else -2
            if s == -2:
                return -1 - row, fix[:nfix]  # too many cells
            if s < 0:  # skip this cell
                while i < n and buf[i] != 44 and buf[i] != 10:
                    i += 1
            else:
                start = i
                neg = False
                if i < n and (buf[i] == 45 or buf[i] == 43):
                    neg = buf[i] == 45
                    i += 1
                digits_start = i
                mant = 0
                dropped = False
                digits = 0
                frac = 0
                seen = False
                dot = False
                while i < n:
                    c = buf[i]
                    if 48 <= c <= 57:
                        seen = True
                        if digits < 18:
                            mant = mant * 10 + (c - 48)
                            digits += mant > 0
                            if dot:
                                frac += 1
                        else:
                            dropped = True
                            if not dot:
                                frac -= 1  # dropped integer digit
                        i += 1
                    elif c == 46 and not dot:
                        dot = True
                        i += 1
                    else:
                        break
                exp = 0
                if seen and i < n and (buf[i] == 101 or buf[i] == 69):
                    i += 1
                    eneg = False
                    if i < n and (buf[i] == 45 or buf[i] == 43):
                        eneg = buf[i] == 45
                        i += 1
                    ed = False
                    while i < n and 48 <= buf[i] <= 57:
                        exp = exp * 10 + (buf[i] - 48)
                        ed = True
                        i += 1
                    if not ed:
                            return -1 - row, fix[:nfix]
                    if eneg:
                        exp = -exp
                if seen:
                    e10 = exp - frac
                    v = float(mant)
                    if dropped or mant > 9007199254740992 or e10 < -22 or e10 > 22:
                        if nfix == fix.shape[0]:
                            grown = np.empty((2 * nfix, 5), dtype=np.int64)
                            grown[:nfix] = fix
                            fix = grown
                        fix[nfix, 0] = row
                        fix[nfix, 1] = s
                        fix[nfix, 2] = digits_start
                        fix[nfix, 3] = i
                        fix[nfix, 4] = neg
                        nfix += 1
                        v = 0.0  # converted exactly by the caller
                    elif e10 < 0:
                        v = v / pow10[-e10]
                    elif e10 > 0:
                        v = v * pow10[e10]
                    out[row, s] = -v if neg else v
                elif i == start and (i >= n or buf[i] == 44 or buf[i] == 10):
                    out[row, s] = np.nan  # empty cell
                elif (i + 2 < n and (buf[i] == 110 or buf[i] == 78)
                      and (buf[i + 1] == 97 or buf[i + 1] == 65)
                      and (buf[i + 2] == 110 or buf[i + 2] == 78)):
                    i += 3
                    out[row, s] = np.nan
                elif (i + 2 < n and (buf[i] == 105 or buf[i] == 73)
                      and (buf[i + 1] == 110 or buf[i + 1] == 78)
                      and (buf[i + 2] == 102 or buf[i + 2] == 70)):
                    i += 3
                    out[row, s] = -np.inf if neg else np.inf
                else:
                    return -1 - row, fix[:nfix]
                if i < n and buf[i] != 44 and buf[i] != 10:
                    return -1 - row, fix[:nfix]  # junk after the number
            col += 1
            if i >= n or buf[i] == 10:
                if col != ncols:
                    return -1 - row, fix[:nfix]  # too few cells
                i += 1
                break
            i += 1  # the comma
        row += 1
    return row, fix[:nfix]


def _convert_exactly(body: bytes, fix: np.ndarray, out: np.ndarray) -> None:
    """The cells ``_parse`` noted (row, slot, start, end, negative) converted by pyarrow's
    correctly rounded string-to-float cast (all at once, no Python loop)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    bounds = np.empty(2 * len(fix), dtype=np.int64)
    bounds[0::2], bounds[1::2] = fix[:, 2], fix[:, 3]  # cells and the gaps between them
    offsets = pa.py_buffer(np.append(bounds, fix[-1, 3]).astype(np.int64))
    cells = pa.LargeStringArray.from_buffers(len(bounds), offsets, pa.py_buffer(body))
    try:
        cast = pc.cast(cells[0::2], pa.float64())
        # its value buffer read directly: to_numpy(zero_copy_only=False) imports pandas
        # (0.4 s of every command that reads a session)
        values = np.frombuffer(cast.buffers()[1], dtype=np.float64)[
            cast.offset : cast.offset + len(cast)
        ]
    except pa.ArrowInvalid:  # beyond float64 (1e400): float() says inf
        values = np.array([float(body[a:b]) for a, b in zip(fix[:, 2], fix[:, 3], strict=True)])
    out[fix[:, 0], fix[:, 1]] = np.where(fix[:, 4] != 0, -values, values)


def parse_numeric(
    body: bytes, header: list[str], columns: list[str]
) -> dict[str, np.ndarray] | None:
    """The ``columns`` of CSV ``body`` (lines after the header, '\\n'-separated) as float64
    arrays, or None when a cell or line does not parse (see the module docstring)."""
    if not body:
        return {c: np.zeros(0) for c in columns}
    buf = np.frombuffer(body, dtype=np.uint8)
    nrows = body.count(b"\n") + (0 if body.endswith(b"\n") else 1)
    slot = np.full(len(header), -1, dtype=np.int64)
    for k, c in enumerate(columns):
        slot[header.index(c)] = k
    out = np.empty((nrows, len(columns)))
    got, fix = _parse(buf, len(header), slot, len(columns), out)
    if got != nrows:
        return None
    if len(fix):
        _convert_exactly(body, fix, out)
    return {c: np.ascontiguousarray(out[:, k]) for k, c in enumerate(columns)}
