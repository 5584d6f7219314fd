"""Sessions → analysis inputs: validation, metadata, cycles, uniform grids."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from smabench.analysis.candidates import (
    CP_J_KGK,
    G_M_S2,
    RESISTIVITY_MEAN_OHM_M,
    RHO_KG_M3,
)
from smabench.analysis.model import Grid
from smabench.physics.wire import PAPER_WIRE
from smabench.sessions import FLAGS_POSITION_INVALID

DEFAULT_LENGTH_MM = PAPER_WIRE.length_mm
DEFAULT_DIAMETER_MM = PAPER_WIRE.diameter_mm
DEFAULT_AMBIENT_C = 22.0


class AnalysisError(ValueError):
    """Input the analysis cannot use (the user's fault): one clear line."""


@dataclass
class SessionData:
    """One session's samples (original times) plus what the analysis derives from them."""

    name: str
    path: str
    kind: str  # "current" or "thermo"
    t: np.ndarray
    pos: np.ndarray
    current: np.ndarray | None
    voltage: np.ndarray | None
    ambient: np.ndarray | None
    temp: np.ndarray | None
    cycle: np.ndarray  # int cycle index per sample
    n_complete: int
    load_kg: float | None
    stress_mpa: float | None
    length_mm: float
    diameter_mm: float
    row_time: bool  # t is the row index (no t_s column)
    notes: list[str]
    valid: np.ndarray | None = None  # bool per sample: a position to compare with (None: all)
    cut: dict | None = None  # rows cut before the analysis (a loading ramp, an unloading)

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = np.isfinite(self.pos)

    @property
    def masked_rows(self) -> int:
        """Rows whose position is flagged invalid or empty: simulated through, not compared."""
        return int(np.count_nonzero(~self.valid))

    @property
    def area_m2(self) -> float:
        return math.pi * (self.diameter_mm * 0.5e-3) ** 2

    @property
    def heat_capacity_j_k(self) -> float:
        return RHO_KG_M3 * CP_J_KGK * self.area_m2 * self.length_mm * 1e-3

    def resistance_ohm(self) -> tuple[float, str]:
        """Mean wire resistance, Ω: median V/I when the voltage is recorded, else nominal."""
        if self.voltage is not None and self.current is not None:
            i = self.current
            ok = np.isfinite(self.voltage) & (i > 0.2 * np.nanmax(i)) & (i > 0.02)
            if ok.sum() >= 10:
                return float(np.median(self.voltage[ok] / i[ok])), "median V/I"
        r = RESISTIVITY_MEAN_OHM_M * self.length_mm * 1e-3 / self.area_m2
        return r, "nominal 90 µΩ·cm"

    def noise_mm(self) -> float:
        """Sensor noise std from the sample-to-sample differences (robust)."""
        d = np.diff(self.pos[self.valid])
        if len(d) < 3:
            return 0.0
        mad = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))
        # quantised readings: most differences are 0 and the MAD says 0; the quantisation
        # itself is then the floor (uniform rounding error, step/√12)
        steps = np.abs(d[d != 0])
        quant = float(np.min(steps)) / math.sqrt(12.0) if len(steps) else 0.0
        return max(mad, quant)


def _finite_column(data: dict, name: str, path: str) -> np.ndarray:
    col = np.asarray(data[name], dtype=float)
    bad = ~np.isfinite(col)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise AnalysisError(
            f"{path}: column {name} has {bad.sum()} empty/NaN value(s) (first at data row "
            f"{rows[0] + 1}); the analysis needs it complete"
        )
    return col


MIN_VALID_FRACTION = 0.5
"""At least this share of the rows must hold a valid position."""


def _position(data: dict, path: str) -> tuple[np.ndarray, np.ndarray]:
    """``position_mm`` and the mask of rows that hold a valid one: rows whose ``flags`` mark the
    position invalid (:data:`smabench.sessions.FLAGS_POSITION_INVALID`) or whose position is
    empty are masked (the model is simulated through them; their residuals are dropped)."""
    pos = np.asarray(data["position_mm"], dtype=float)
    valid = np.isfinite(pos)
    flags = data.get("flags")
    if flags is not None:
        f = np.asarray(flags, dtype=float)
        ok = np.isfinite(f)
        bits = np.zeros(len(f), dtype=np.int64)
        bits[ok] = f[ok].astype(np.int64)
        valid &= (bits & FLAGS_POSITION_INVALID) == 0
    if valid.sum() < max(20, MIN_VALID_FRACTION * len(pos)):
        raise AnalysisError(
            f"{path}: only {int(valid.sum())} of {len(pos)} rows hold a valid position_mm "
            "(empty or flagged invalid); the analysis needs most of them"
        )
    pos = np.where(valid, pos, np.nan)
    return pos, valid


HOLD_TOLERANCE = 0.05
"""A row is at the hold stress when its stress is within this fraction of the hold's."""


def _cut_to_hold(data: dict) -> tuple[dict, dict | None]:
    """An isobaric test as a testing machine exports it: the loading ramp up to the hold stress
    before the cycling (and an unloading after it) is not isobaric cycling. With a
    ``stress_MPa`` column, the hold stress is its median (the hold is most of the test); the rows
    before the stress first comes within :data:`HOLD_TOLERANCE` of it and after it last was are
    cut. Returns the data (cut or as given) and what was cut (None: nothing)."""
    if "stress_MPa" not in data:
        return data, None
    stress = np.asarray(data["stress_MPa"], dtype=float)
    ok = np.isfinite(stress)
    if ok.sum() < 20:
        return data, None
    hold = float(np.median(stress[ok]))
    at_hold = ok & (np.abs(stress - hold) <= HOLD_TOLERANCE * abs(hold))
    if hold <= 0 or not at_hold.any():
        return data, None
    k0 = int(np.flatnonzero(at_hold)[0])
    k1 = int(np.flatnonzero(at_hold)[-1]) + 1
    n = len(stress)
    if k0 == 0 and k1 == n:
        return data, None
    text = []
    if k0:
        text.append(f"the loading ramp: first {k0} row(s), stress {np.nanmin(stress[:k0]):.4g} → "
                    f"{stress[k0]:.4g} MPa (hold {hold:.4g} MPa)")  # fmt: skip
    if k1 < n:
        text.append(f"the unloading: last {n - k1} row(s), after the stress left the hold "
                    f"{hold:.4g} MPa ± {HOLD_TOLERANCE:.0%}")  # fmt: skip
    cut = {"loading_rows": k0, "unloading_rows": n - k1, "hold_stress_mpa": hold, "text": text}
    out = {}
    for name, col in data.items():
        out[name] = col[k0:k1] if len(col) == n else col
    return out, cut


FOLLOW_TOLERANCE = 0.03
"""The measured current follows the command when their steady levels differ by less than this
fraction of the largest current (median over the steady rows)."""


LOOKAHEAD_ROWS = 3
"""Rows within which the telemetry shows a commanded current (it reports one or two late)."""


def commanded_timing(measured: np.ndarray, commanded: np.ndarray) -> tuple[np.ndarray, str]:
    """The wire's current, A, per row as applied from that row's time to the next's.

    A bench session records the commanded current (``current_set_A``) at the tick that commands
    it, and the measured one (``current_A``) from the driver's last telemetry frame: up to a
    period or two late, by a lag that varies with the frame's phase (on the 5× mock: the
    recorded switching instants scatter by ±25 ms against the plant's, while the commanded ones
    stay within 5 ms of a fixed latency; a one-sample error in the switching instant moves a
    sharp transformation by 0.1–0.3 mm). When the measured current follows the command (its
    next row, over the rows where the command is steady, equals gain × command within
    :data:`FOLLOW_TOLERANCE`), the switching instants are taken from the command and the level
    from the measurement (gain × command); rows where the driver did not deliver (no measured
    value within :data:`LOOKAHEAD_ROWS` rows reaches half of that) keep the next row's, and so do
    rows commanded off where the driver still delivered (no measured value within
    :data:`LOOKAHEAD_ROWS` rows falls below half the on-level): a command that reached the
    device late (seen on CI: an off 150 ms late in device time, 30 ms of host latency on the 5×
    mock; taken as commanded, that cycle's held-out error went to 94 µm and a nominal recording
    came out ``unexplained``).
    Otherwise (a driver at its limit, a command that moves every tick) the measured current is
    returned as it is.
    Returns the current and a note ('' when unchanged)."""
    n = len(measured)
    if n < 3:
        return measured, ""
    nxt = np.append(measured[1:], measured[-1])
    top = float(np.max(np.abs(commanded)))
    mid = commanded[1:-1]
    steady = np.zeros(n, dtype=bool)
    steady[1:-1] = (mid > 0.05 * top) & (mid == commanded[:-2]) & (mid == commanded[2:])
    if top <= 0 or steady.sum() < 10:
        return measured, ""
    gain = float(np.median(nxt[steady] / commanded[steady]))
    misfit = float(np.median(np.abs(nxt[steady] - gain * commanded[steady])))
    if not (0.8 <= gain <= 1.25 and misfit <= FOLLOW_TOLERANCE * top):
        return measured, ""
    level = gain * commanded
    ahead = np.maximum.reduce([np.append(measured[j:], np.full(j, measured[-1]))
                               for j in range(LOOKAHEAD_ROWS + 1)])  # fmt: skip
    late = (commanded > 0) & (ahead < 0.5 * level)
    on_level = float(np.median(level[steady]))
    behind = np.minimum.reduce([np.append(measured[j:], np.full(j, measured[-1]))
                                for j in range(LOOKAHEAD_ROWS + 1)])  # fmt: skip
    lingering = (level < 0.5 * on_level) & (behind >= 0.5 * on_level)
    out = np.where(late | lingering, nxt, level)
    return out, (f"current switching instants from current_set_A, level from current_A "
                 f"(gain {gain:.3f})")


def _optional(data: dict, name: str) -> np.ndarray | None:
    col = data.get(name)
    if col is None:
        return None
    col = np.asarray(col, dtype=float)
    return col if np.isfinite(col).any() else None


def _cycles_from_current(current: np.ndarray) -> tuple[np.ndarray, int]:
    """Cycle index from heating pulses (rising edges); complete = a pulse that ended."""
    on = current > 0.05 * max(float(np.max(current)), 1e-9)
    rise = np.flatnonzero(on[1:] & ~on[:-1]) + 1
    if on[0]:
        rise = np.concatenate(([0], rise))
    fall = np.flatnonzero(~on[1:] & on[:-1]) + 1
    cycle = np.zeros(len(current), dtype=int)
    if len(rise):
        cycle = np.maximum(np.searchsorted(rise, np.arange(len(current)), side="right") - 1, 0)
    complete = sum(1 for r in rise.tolist() if np.any((fall > r) & (fall < len(current) - 2)))
    return cycle, complete


def _cycles_from_temperature(temp: np.ndarray) -> tuple[np.ndarray, int]:
    """Cycle boundaries at temperature minima (hysteresis on the extrema).

    A complete cycle goes min → max → min."""
    span = float(np.ptp(temp))
    if span <= 0:
        return np.zeros(len(temp), dtype=int), 0
    h = 0.3 * span
    # zig-zag extrema with threshold h
    ext = [(0, "min" if temp[1:].mean() >= temp[0] else "max")] if len(temp) > 1 else []
    lo_i = hi_i = 0
    state = ext[0][1] if ext else "min"
    for k in range(1, len(temp)):
        v = temp[k]
        if state == "min":  # looking for a max after a min
            if v > temp[hi_i]:
                hi_i = k
            if v < temp[lo_i] and hi_i < lo_i:
                lo_i = k
            if temp[hi_i] - v > h and hi_i > lo_i:
                ext.append((hi_i, "max"))
                state, lo_i = "max", k
        else:
            if v < temp[lo_i]:
                lo_i = k
            if v - temp[lo_i] > h and lo_i > hi_i:
                ext.append((lo_i, "min"))
                state, hi_i = "min", k
    mins = [i for i, kind in ext if kind == "min"]
    maxs = [i for i, kind in ext if kind == "max"]
    # the end of the record counts as a minimum when it came back down by h
    last_max = maxs[-1] if maxs else None
    if last_max is not None and temp[last_max] - temp[-1] > h:
        mins.append(len(temp) - 1)
    complete = sum(1 for m in maxs if any(a < m for a in mins) and any(b > m for b in mins))
    starts = sorted(i for i in mins if i < len(temp) - 1)
    cycle = np.zeros(len(temp), dtype=int)
    if starts:
        cycle = np.maximum(np.searchsorted(starts, np.arange(len(temp)), side="right") - 1, 0)
    return cycle, complete


def prepare_session(
    session,
    load_kg: float | None = None,
    length_mm: float | None = None,
    diameter_mm: float | None = None,
) -> SessionData:
    """Validate a loaded :class:`smabench.sessions.Session` and extract the analysis inputs.

    Flags (``load_kg``, ``length_mm``, ``diameter_mm``) override ``session.json``.
    """
    path = str(session.path)
    data = session.data
    meta = session.meta or {}
    notes: list[str] = []
    if "position_mm" not in data:
        raise AnalysisError(f"{path}: no position_mm column")
    has_current = "current_A" in data and _optional(data, "current_A") is not None
    has_temp = "temperature_C" in data and _optional(data, "temperature_C") is not None
    if has_current and "t_s" in data and not meta.get("t_s_is_row_index"):
        kind = "current"
    elif has_temp:
        kind = "thermo"
    else:
        raise AnalysisError(
            f"{path}: needs t_s, current_A and position_mm (current-driven) or temperature_C and "
            f"position_mm (thermometer loop); columns: {', '.join(session.columns)}"
        )
    data, cut = _cut_to_hold(data)
    n = len(data["position_mm"])
    if n < 20:
        raise AnalysisError(f"{path}: only {n} samples; the analysis needs at least 20")
    pos, valid = _position(data, path)
    t = _finite_column(data, "t_s", path)
    row_time = bool(meta.get("t_s_is_row_index"))
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise AnalysisError(f"{path}: t_s does not increase at data row {k + 2}")
    wire = meta.get("wire") or {}
    length = length_mm or wire.get("length_mm")
    diameter = diameter_mm or wire.get("diameter_mm")
    if length is None:
        length = DEFAULT_LENGTH_MM
        notes.append(f"wire length not given: {DEFAULT_LENGTH_MM} mm assumed (--wire-length-mm)")
    if diameter is None:
        diameter = DEFAULT_DIAMETER_MM
        notes.append(
            f"wire diameter not given: {DEFAULT_DIAMETER_MM} mm assumed (--wire-diameter-mm)"
        )
    length, diameter = float(length), float(diameter)
    if not (0 < length < 1e5 and 0 < diameter < 10):
        raise AnalysisError(f"{path}: implausible wire length {length} mm / diameter {diameter} mm")
    load = load_kg if load_kg is not None else meta.get("load_kg")
    load = None if load is None else float(load)
    area = math.pi * (diameter * 0.5e-3) ** 2
    stress = None
    current = voltage = ambient = temp = None
    if kind == "current":
        current = _finite_column(data, "current_A", path)
        commanded = _optional(data, "current_set_A")
        if commanded is not None and np.isfinite(commanded).all():
            current, note = commanded_timing(current, commanded)
            if note:
                notes.append(note)
        voltage = _optional(data, "voltage_V")
        ambient = _optional(data, "ambient_C")
        if ambient is not None and not np.isfinite(ambient).all():
            ok = np.isfinite(ambient)
            ambient = np.interp(np.arange(n), np.flatnonzero(ok), ambient[ok])
        if load is not None:
            stress = load * G_M_S2 / area * 1e-6
        cyc = _optional(data, "cycle")
        cycle, complete = _cycles_from_current(current)
        if cyc is not None and np.isfinite(cyc).all() and np.all(np.diff(cyc) >= 0):
            cycle = (cyc - cyc[0]).astype(int)
        if complete == 0:
            raise AnalysisError(
                f"{path}: no complete cycle (a heating pulse followed by cooling with the "
                "current off); nothing to analyse"
            )
    else:
        temp = _finite_column(data, "temperature_C", path)
        if "stress_MPa" in data and _optional(data, "stress_MPa") is not None:
            stress = float(np.nanmean(data["stress_MPa"]))
            if load_kg is not None:
                stress = load_kg * G_M_S2 / area * 1e-6
        elif load is not None:
            stress = load * G_M_S2 / area * 1e-6
        cycle, complete = _cycles_from_temperature(temp)
        if complete == 0:
            raise AnalysisError(
                f"{path}: no complete cycle (the temperature never rises and falls back by 30 % "
                "of its range); nothing to analyse"
            )
    if load is None and stress is not None:
        load = stress * 1e6 * area / G_M_S2
    if stress is None:
        notes.append("load not given: the elastic stroke and any stress question are left "
                     "out (--load-kg)")
    if np.ptp(pos[valid]) <= 0:
        raise AnalysisError(f"{path}: position_mm never changes")
    name = Path(path).name or path
    return SessionData(
        name=name, path=path, kind=kind, t=t, pos=pos, current=current, voltage=voltage,
        ambient=ambient, temp=temp, cycle=cycle, n_complete=complete, load_kg=load,
        stress_mpa=stress, length_mm=length, diameter_mm=diameter, row_time=row_time, notes=notes,
        valid=valid, cut=cut,
    )  # fmt: skip


def make_grid(s: SessionData, dt: float | None, stress_mpa: float) -> tuple[Grid, np.ndarray]:
    """The session on a uniform grid of step ``dt`` (None: median sample step); returns the
    grid and the grid index of every original sample (thermometer loops: the samples)."""
    r_ohm, _ = s.resistance_ohm() if s.kind == "current" else (1.0, "")
    if s.kind == "thermo":
        dts = float(np.median(np.diff(s.t)))
        g = Grid(
            s.name, "thermo", s.t, dts, None, None, s.temp, stress_mpa, s.length_mm,
            s.heat_capacity_j_k, r_ohm,
        )  # fmt: skip
        return g, np.arange(len(s.t))
    if dt is None:
        dt = float(np.median(np.diff(s.t)))
    t0, t1 = float(s.t[0]), float(s.t[-1])
    m = int(math.floor((t1 - t0) / dt)) + 1
    tg = t0 + dt * np.arange(m)
    # energy of the zero-order-held I²: cumulative integral is piecewise linear → exact interp
    cum = np.concatenate(([0.0], np.cumsum(s.current[:-1] ** 2 * np.diff(s.t))))
    e = np.interp(tg, s.t, cum)
    i2 = np.diff(e) / dt
    amb_src = s.ambient if s.ambient is not None else np.full(len(s.t), DEFAULT_AMBIENT_C)
    amb = np.interp(tg, s.t, amb_src)
    g = Grid(
        s.name, "current", tg, dt, i2, amb, None, stress_mpa, s.length_mm,
        s.heat_capacity_j_k, r_ohm,
    )  # fmt: skip
    idx = np.clip(np.rint((s.t - t0) / dt).astype(int), 0, m - 1)
    return g, idx


ANALYSIS_BYTES_PER_ROW = 2048
"""Memory the analysis holds per sample row (the loaded columns, the grids, every candidate's
simulation): measured peak resident memory 212 MB for a 5 600-row session and 293 MB for a
56 000-row one, 1.6 kB a row, rounded up."""


def estimated_rows(path: str | Path) -> int:
    """A session's sample rows, estimated from its files' sizes and the length of its first
    lines (no parsing: the estimate comes before any load)."""
    from smabench.sessions import sample_files

    p = Path(path)
    files = sample_files(p) if p.is_dir() else [p] if p.is_file() else []
    if not files:
        return 0
    with open(files[0], "rb") as fh:
        head = fh.read(65536)
    lines = head.count(b"\n")
    if lines < 2:
        return lines
    per_row = len(head[head.index(b"\n") + 1 : head.rindex(b"\n") + 1]) / (lines - 1)
    return int(sum(f.stat().st_size for f in files) / max(per_row, 1.0))


def require_memory(paths: list[str], processes: int = 1, each: bool = False) -> None:
    """Refuse up front (:class:`smabench.memlimit.NotEnoughMemoryError`, exit 2) when analysing
    ``paths`` needs more memory than is free: all of them at once (joint), or with ``each`` the
    largest one in each of ``processes`` workers. The analysis holds whole sessions: it is not
    streamed."""
    from smabench.memlimit import require

    rows = {str(p): estimated_rows(p) for p in paths}
    if each:
        where, n = max(rows.items(), key=lambda kv: kv[1])
        what = f"analysing {where} (about {n:,} rows)".replace(",", " ")
    else:
        n = sum(rows.values())
        what = f"analysing {len(rows)} session(s) together (about {n:,} rows)".replace(",", " ")
    require(ANALYSIS_BYTES_PER_ROW * n, what, processes if each else 1)
