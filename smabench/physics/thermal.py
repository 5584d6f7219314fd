"""Heat balance of the wire, eq. (16): ``m·cp·dT/dt = -h·A·(T - T_room) + I²·R``.

With the current held constant over a step (zero-order hold, as a current source does) the ODE
is linear with constant coefficients, so each step has the exact solution

    T(t+dt) = T_inf + (T(t) - T_inf)·exp(-dt/tau),  tau = m·cp/(h·A),  T_inf = T_room + I²R/(h·A)

Everything here uses that exact step: no integration error whatever the step size. Over a
uniformly sampled profile it is a first-order linear recurrence, run by ``scipy.signal.lfilter``
(≈ 1e8 samples/s). Temperatures in °C, currents in A, times in s, resistances in Ω.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from smabench.physics.wire import Wire

log = logging.getLogger(__name__)

ArrayLike = float | np.ndarray


def thermal_constants(wire: Wire) -> tuple[float, float]:
    """Heat capacity m·cp, J/K, and conductance h·A, W/K, of ``wire``."""
    return wire.mass_kg * wire.cp_j_kgk, wire.h_w_m2k * wire.surface_m2


def time_constant_s(wire: Wire) -> float:
    """Thermal time constant tau = m·cp/(h·A), s (≈ 4 s for the paper's wire)."""
    heat_capacity, conductance = thermal_constants(wire)
    return heat_capacity / conductance


def step_exact(
    temperature_c: ArrayLike,
    current_a: ArrayLike,
    dt_s: ArrayLike,
    wire: Wire,
    ambient_c: ArrayLike = 22.0,
    resistance_ohm: ArrayLike | None = None,
) -> ArrayLike:
    """Wire temperature, °C, after ``dt_s`` s at a constant ``current_a`` (exact solution).

    All arguments broadcast (numpy arrays or floats). ``resistance_ohm`` defaults to the wire's
    mean-phase resistance.
    """
    heat_capacity, conductance = thermal_constants(wire)
    r = wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
    t_inf = ambient_c + np.square(current_a) * r / conductance
    decay = np.exp(-np.asarray(dt_s, dtype=float) * conductance / heat_capacity)
    out = t_inf + (temperature_c - t_inf) * decay
    return float(out) if np.ndim(out) == 0 else out


def linear_recurrence(a: ArrayLike, u: np.ndarray, x0: float) -> np.ndarray:
    """Solve ``x[n+1] = a[n]·x[n] + u[n]``, x[0] = x0; returns x of length len(u) + 1.

    Compiled (numba, cached): a command that simulates then needs no ``scipy.signal``, whose
    import alone took 1.5 s of ``smabench simulate``'s 3.1 s.
    """
    u = np.asarray(u, dtype=float)
    out = np.empty(len(u) + 1)
    out[0] = x0
    if len(u) == 0:
        return out
    a_arr = np.broadcast_to(np.asarray(a, dtype=float), u.shape)
    _recurrence(np.ascontiguousarray(a_arr), u, float(x0), out)
    return out


@njit(cache=True, nogil=True)
def _recurrence(a, u, x0, out):  # pragma: no cover - compiled
    x = x0
    for n in range(u.size):
        x = a[n] * x + u[n]
        out[n + 1] = x


def simulate_temperature(
    t_s: np.ndarray,
    current_a: ArrayLike,
    wire: Wire,
    ambient_c: ArrayLike = 22.0,
    T0: float | None = None,
    resistance_ohm: float | None = None,
) -> np.ndarray:
    """Temperature, °C, at the sample times ``t_s`` (s, increasing) of a current profile.

    ``current_a[n]`` (A) and ``ambient_c[n]`` (°C, scalar or array) are held from ``t_s[n]`` to
    ``t_s[n+1]``; ``T0`` (°C) is the temperature at ``t_s[0]`` (default: the first ambient).
    Exact for that zero-order hold, vectorised (lfilter) when the step is uniform.
    """
    t_s = np.asarray(t_s, dtype=float)
    n = len(t_s)
    cur = np.broadcast_to(np.asarray(current_a, dtype=float), (n,))
    amb = np.broadcast_to(np.asarray(ambient_c, dtype=float), (n,))
    if n == 0:
        return np.empty(0)
    x0 = float(amb[0] if T0 is None else T0)
    heat_capacity, conductance = thermal_constants(wire)
    r = wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
    dt = np.diff(t_s)
    if len(dt) and np.allclose(dt, dt[0], rtol=1e-9, atol=0.0):
        a: ArrayLike = math.exp(-float(dt[0]) * conductance / heat_capacity)
    else:
        a = np.exp(-dt * conductance / heat_capacity)
    t_inf = amb[:-1] + cur[:-1] ** 2 * r / conductance
    return linear_recurrence(a, (1.0 - np.asarray(a)) * t_inf, x0)


def steady_state_temperature(
    current_a: ArrayLike,
    wire: Wire,
    ambient_c: ArrayLike = 22.0,
    resistance_ohm: ArrayLike | None = None,
) -> ArrayLike:
    """Steady wire temperature, °C, at a constant ``current_a``: T_room + I²R/(h·A)."""
    _, conductance = thermal_constants(wire)
    r = wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
    out = ambient_c + np.square(current_a) * r / conductance
    return float(out) if np.ndim(out) == 0 else out


def current_for_steady_temperature(
    temperature_c: ArrayLike,
    wire: Wire,
    ambient_c: ArrayLike = 22.0,
    resistance_ohm: ArrayLike | None = None,
) -> ArrayLike:
    """Current, A (≥ 0), that holds the wire at ``temperature_c``; 0 at or below ambient."""
    _, conductance = thermal_constants(wire)
    r = wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
    out = np.sqrt(np.maximum(0.0, (np.asarray(temperature_c) - ambient_c) * conductance / r))
    return float(out) if np.ndim(out) == 0 else out


def current_for_trajectory(
    t_s: np.ndarray,
    temperature_c: np.ndarray,
    wire: Wire,
    ambient_c: ArrayLike = 22.0,
    resistance_ohm: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Current that makes the wire follow ``temperature_c`` at the sample times ``t_s``.

    Inverts the exact step: ``current_a[n]`` held over [t_n, t_n+1) takes T[n] to T[n+1].
    Cooling is passive: where the trajectory falls faster than natural cooling allows, the
    current is clipped to 0 and ``clipped[n]`` is True (the wire then lags the trajectory).
    Returns ``(current_a, clipped)``, both of len(t_s); the last sample repeats the previous.
    """
    t_s = np.asarray(t_s, dtype=float)
    temp = np.asarray(temperature_c, dtype=float)
    n = len(t_s)
    amb = np.broadcast_to(np.asarray(ambient_c, dtype=float), (n,))
    heat_capacity, conductance = thermal_constants(wire)
    r = wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
    if n < 2:
        return np.zeros(n), np.zeros(n, dtype=bool)
    a = np.exp(-np.diff(t_s) * conductance / heat_capacity)
    t_inf = (temp[1:] - a * temp[:-1]) / (1.0 - a)
    i2 = (t_inf - amb[:-1]) * conductance / r
    clipped = i2 < -1e-12
    cur = np.sqrt(np.maximum(i2, 0.0))
    return np.append(cur, cur[-1]), np.append(clipped, clipped[-1])


class TemperatureEstimator:
    """Online wire-temperature estimate from the measured current (and voltage, when known).

    Each ``update`` is one exact heat-balance step with the electrical power held over the step:
    ``V·I`` when the wire voltage is measured (so a wrong resistance assumption does not bias
    the estimate), else ``I²·R_assumed``. O(1), plain Python floats (≈ 1 µs per update).
    """

    def __init__(
        self,
        wire: Wire,
        ambient_c: float = 22.0,
        temperature_c: float | None = None,
        resistance_ohm: float | None = None,
        min_current_for_resistance_a: float = 0.02,
    ) -> None:
        self.wire = wire
        self.ambient_c = float(ambient_c)
        self.temperature_c = float(ambient_c if temperature_c is None else temperature_c)
        self.resistance_assumed_ohm = float(
            wire.resistance_mean_ohm if resistance_ohm is None else resistance_ohm
        )
        self.min_current_a = min_current_for_resistance_a
        self.measured_resistance_ohm: float | None = None
        """Last V/I, Ω (None until a voltage at ≥ min_current_for_resistance_a arrives)."""
        self.power_w = 0.0
        heat_capacity, conductance = thermal_constants(wire)
        self._rate = conductance / heat_capacity
        self._conductance = conductance
        self._dt_cache = (-1.0, 1.0)

    def reset(self, temperature_c: float | None = None) -> None:
        """Restart from ``temperature_c`` (default: ambient)."""
        self.temperature_c = self.ambient_c if temperature_c is None else float(temperature_c)
        self.measured_resistance_ohm = None

    def update(
        self,
        dt_s: float,
        current_a: float,
        voltage_v: float | None = None,
        ambient_c: float | None = None,
    ) -> float:
        """Advance ``dt_s`` s with ``current_a`` (A), optional wire ``voltage_v`` (V) and
        ``ambient_c`` (°C); returns the estimated temperature, °C."""
        if ambient_c is not None and ambient_c == ambient_c:
            self.ambient_c = ambient_c
        if (
            voltage_v is not None
            and voltage_v == voltage_v
            and abs(current_a) >= self.min_current_a
        ):
            power = voltage_v * current_a
            self.measured_resistance_ohm = voltage_v / current_a
        else:
            power = current_a * current_a * self.resistance_assumed_ohm
        self.power_w = power
        if dt_s != self._dt_cache[0]:
            self._dt_cache = (dt_s, math.exp(-dt_s * self._rate))
        decay = self._dt_cache[1]
        t_inf = self.ambient_c + power / self._conductance
        self.temperature_c = t_inf + (self.temperature_c - t_inf) * decay
        return self.temperature_c
