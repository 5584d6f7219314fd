"""A nominal session recorded on the mock bench must give the baseline a held-out fit as good as
its training fit in every fold (issue 24: one recording beside two CPU burners came out
``ambient_drift``: in the fold that held its first cycle out, the baseline fitted the training
cycles as well as the other folds but missed the held-out one by 1.2 mm)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from smabench.analysis import core
from smabench.analysis.core import _project, fit_model, make_folds, make_problem, predict
from smabench.analysis.data import prepare_session
from smabench.analysis.model import LINEAR
from smabench.sessions import load_session

S1 = Path(__file__).resolve().parent / "data" / "nominal-1kg-s1"
"""The recording analyze named ``ambient_drift`` (3 cycles, 1 kg, 5× mock, seed 0, beside two
burners), columns trimmed to what the analysis reads."""


OPEN_FIX = pytest.mark.xfail(
    strict=True,
    reason="open: the monotone map tried in ac1710d (|eps_mix| <= |eps_L| in _project) broke "
    "test_analysis_third's drift-on-top and lag-on-none cases (sensor_lag named); reverted. Its "
    "other half, the shape screens from the two best taus, is in (TAU_STARTS)",
)


def lstsq_with_offsets(basis: np.ndarray, y: np.ndarray, rows: np.ndarray,
                       tie: float | None = None) -> tuple[np.ndarray, float]:  # fmt: skip
    """Reference: lstsq on the basis and one offset per block (``tie``: ε_mix = tie·ε_L)."""
    cols = basis.copy()
    if tie is not None:
        cols = np.column_stack((basis[:, 0] + tie * basis[:, 2], basis[:, 1], basis[:, 3]))
    blocks = np.zeros((len(y), len(rows) - 1))
    for s in range(len(rows) - 1):
        blocks[rows[s]:rows[s + 1], s] = 1.0
    design = np.column_stack((cols, blocks))
    sol, *_ = np.linalg.lstsq(design, y, rcond=None)
    ssr = float(np.sum((y - design @ sol) ** 2))
    coef = sol[:cols.shape[1]]
    if tie is not None:
        coef = np.array([coef[0], coef[1], tie * coef[0], coef[2]])
    return coef, ssr


def xi_basis(xi: np.ndarray, temp: np.ndarray, ds: np.ndarray | float) -> np.ndarray:
    """The columns of :data:`LINEAR` for a 55 mm wire (``ds``: σ − σ_ref, MPa)."""
    l0 = 55.0
    return np.column_stack((l0 * xi, l0 * (temp - 22.0), l0 * xi * (1 - xi), l0 * ds * xi))


@OPEN_FIX
def test_the_length_map_stays_monotone_in_xi():
    """ξ cycling between 0 and ½ (the cooling branch's centre at the room's temperature): a map
    ε_mix·ξ(1-ξ) alone fits it; the projection keeps |ε_mix| ≤ |ε_L| (the mixture's length
    between its phases') and returns the better face of that bound, as lstsq finds it."""
    rng = np.random.default_rng(3)
    n = 400
    xi = 0.25 * (1.0 + np.sin(np.linspace(0.0, 12.0, n)))  # 0 … 0.5
    temp = 22.0 + 40.0 * (0.5 - xi) + rng.normal(0.0, 3.0, n)  # not collinear with ξ
    basis = xi_basis(xi, temp, 0.0)  # one load: its column drops out
    y = 0.18 * basis[:, 2] + 1.1e-5 * basis[:, 1] + 1.7 + rng.normal(0.0, 0.003, n)
    rows = np.array([0, n], dtype=np.int64)
    free, _ = lstsq_with_offsets(basis, y, rows)
    assert abs(free[2]) > 3.0 * abs(free[0])  # unconstrained: the bent map carries the stroke
    r, coef, _off = _project(basis, y, rows)
    eps_l, eps_mix = coef[LINEAR.index("eps_l")], coef[LINEAR.index("eps_mix")]
    assert abs(eps_mix) <= abs(eps_l) * (1.0 + 1e-9)
    faces = [lstsq_with_offsets(basis, y, rows, tie) for tie in (1.0, -1.0)]
    best_coef, best_ssr = min(faces, key=lambda f: f[1])
    assert float(np.sum(r**2)) == pytest.approx(best_ssr, rel=1e-9)
    np.testing.assert_allclose(coef, best_coef, rtol=1e-6, atol=1e-12)


def test_a_monotone_map_is_solved_as_before():
    """Inside the bound nothing changes: the projection is lstsq's (two sessions' zeros)."""
    rng = np.random.default_rng(4)
    n = 600
    xi = 0.5 * (1.0 + np.sin(np.linspace(0.0, 20.0, n)))
    temp = 22.0 + 50.0 * (1.0 - xi) + rng.normal(0.0, 1.0, n)
    basis = xi_basis(xi, temp, rng.normal(0.0, 10.0, n))
    y = basis @ np.array([0.045, 1.1e-5, 0.002, 1e-5]) + rng.normal(0.0, 0.003, n)
    y[300:] += 0.4
    rows = np.array([0, 300, n], dtype=np.int64)
    ref, ssr = lstsq_with_offsets(basis, y, rows)
    r, coef, _off = _project(basis, y, rows)
    np.testing.assert_allclose(coef, ref, rtol=1e-7, atol=1e-12)
    assert float(np.sum(r**2)) == pytest.approx(ssr, rel=1e-9)


@pytest.fixture(scope="module")
def s1():
    session = prepare_session(load_session(S1))
    prob = make_problem([session])
    return session, prob, make_folds(prob)


def test_every_fold_of_the_nominal_session_predicts_its_held_out_cycle(s1):
    """Each fold's own baseline fit (no consensus from the other folds) keeps the physical
    length map and time constant, and predicts the held-out cycle to a fraction of a millimetre.
    Before: the fold holding the first cycle out fitted τ = 1.0 s with ε_L ≈ 0 and
    ε_mix = 0.18 (train 0.0074 mm, held-out 1.17 mm; CI: a fresh 2 kg recording, 0.63 mm
    pooled). The shape screens from the two best thermal time constants (TAU_STARTS) find the
    physical basin: 0.094 mm there (0.022 and 0.025 mm in the others): the first cycle, the
    only one that starts cold, peaks at 76 °C against the others' 82 °C and ends its heating
    inside the transformation's upper tail, which the two training cycles leave to
    extrapolation (see the xfail below)."""
    session, prob, folds = s1
    for fold in folds:
        fit = fit_model(prob, fold, "baseline")
        test = fold.test[session.name]
        pred = predict(prob, fit, session, fold.train[session.name])
        held = float(np.sqrt(np.mean((pred.position_mm[test] - session.pos[test]) ** 2)))
        assert fit.train_rmse_mm < 0.009, (fold.name, fit.train_rmse_mm)
        assert held < 0.15, (fold.name, held, fit.values, fit.linear)
        assert abs(fit.linear["eps_mix"]) <= abs(fit.linear["eps_l"]) * (1.0 + 1e-6)
        assert 3.0 < fit.values["tau_s"] < 6.0, (fold.name, fit.values["tau_s"])


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="open: ambient_drift (baseline held-out 0.665 mm; with ac1710d's fix 0.057 mm against "
    "a floor of 0.023 mm: the fold holding the cold-start first cycle out extrapolates the end "
    "of the heating branch, Af 79 °C from the two warm-start cycles while the first cycle "
    "peaks at 76 °C, and ambient_drift is named on top of the rate kinetics, p = 0.0071)",
)
def test_the_nominal_session_comes_out_none(s1):
    session, _prob, _folds = s1
    an = core.analyse([prepare_session(load_session(S1))], workers=1)
    assert an.result["cause"] == "none", an.result["reason"]
    assert an.rmse["baseline"] < 0.05, an.rmse

