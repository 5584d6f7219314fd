"""A compiled reader for the numeric columns of plain CSV text (numba; ≈ 10× numpy's parser).

Used by :mod:`smabench.sessions` for samples files: comma-separated, no quotes, one header line
already removed. Empty cells and ``nan`` read as NaN. A number is read exactly (correctly
rounded, as ``float()``) when it has at most 15 significant digits and 22 decimal places; longer
ones (``repr`` of a float may have 17) are within 1 ulp.
A cell that is not a number in a requested column, or a line with the wrong number of cells,
makes :func:`parse_numeric` return ``None`` so the caller can use a reader that names the line.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _parse(buf, ncols, slot, nwant, out):  # pragma: no cover - compiled
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
                return -1 - row  # too many cells
            if s < 0:  # skip this cell
                while i < n and buf[i] != 44 and buf[i] != 10:
                    i += 1
            else:
                start = i
                neg = False
                if i < n and (buf[i] == 45 or buf[i] == 43):
                    neg = buf[i] == 45
                    i += 1
                mant = 0
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
                        elif not dot:
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
                        return -1 - row
                    if eneg:
                        exp = -exp
                if seen:
                    e10 = exp - frac
                    v = float(mant)
                    if e10 == 0:
                        pass
                    elif -22 <= e10 < 0:
                        v = v / pow10[-e10]
                    elif 0 < e10 <= 22:
                        v = v * pow10[e10]
                    else:
                        v = v * 10.0**e10
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
                    return -1 - row
                if i < n and buf[i] != 44 and buf[i] != 10:
                    return -1 - row  # junk after the number
            col += 1
            if i >= n or buf[i] == 10:
                if col != ncols:
                    return -1 - row  # too few cells
                i += 1
                break
            i += 1  # the comma
        row += 1
    return row


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
    got = _parse(buf, len(header), slot, len(columns), out)
    if got != nrows:
        return None
    return {c: np.ascontiguousarray(out[:, k]) for k, c in enumerate(columns)}
