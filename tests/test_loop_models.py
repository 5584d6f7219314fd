"""Loop models: identification, the online stepper's adaptation rules, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import flexinol_files

from smabench.physics.identify import (
    FitError,
    fit_from_document,
    fit_loop,
    model_document,
    prepare_loop,
)
from smabench.physics.loop_models import (
    CommonPoints,
    LoopStepper,
    Model2,
    branch_directions,
)
from smabench.physics.memory import ReversalMemory, TurnDetector

CLOSED_FORM = ("1", "2", "sigmoid")


def _loop(path):
    a = np.loadtxt(path)
    return a[:, 0], a[:, 1] * 55.0


@pytest.fixture(scope="module")
def fits():
    t, y = _loop(flexinol_files()[0])
    return t, y, {m: fit_loop(t, y, m) for m in CLOSED_FORM}


def test_branch_directions_ignore_noise_inside_deadband():
    t = np.r_[np.linspace(30, 100, 50), np.linspace(100, 30, 50)]
    noisy = t + np.where(np.arange(100) % 2, 0.3, -0.3)
    h = branch_directions(noisy, deadband_k=1.0)
    assert h[:45].all() and not h[55:].any()


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_stepper_follows_major_loop(fits, model):
    t, y, res = fits
    fit = res[model]
    loop = prepare_loop(t, y)
    vec = fit.loop_model.evaluate(t, loop.heating)
    online = fit.predict(t)
    stroke = np.ptp(y)
    # the stepper rescales branches between the reversal points it saw: close to the major loop
    assert np.sqrt(np.mean((online - vec) ** 2)) < 0.01 * stroke


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_incomplete_cycle_starts_at_reversal_point(fits, model):
    """Reheating before the wire cooled: the heating branch starts where cooling stopped."""
    _, y, res = fits
    m = res[model].loop_model
    st = LoopStepper(m, deadband_k=0.5)
    for temp in np.linspace(30, 145, 300):
        st.step(temp)
    cooled = [st.step(temp) for temp in np.linspace(145, 80, 200)]
    reheated = [st.step(temp) for temp in np.linspace(80, 145, 200)]
    stroke = np.ptp(y)
    assert abs(reheated[0] - cooled[-1]) < 0.05 * stroke
    # no jumps along the way
    seq = np.r_[cooled, reheated]
    assert np.max(np.abs(np.diff(seq))) < 0.1 * stroke
    # hot end of the reheat is back on the major loop
    assert abs(reheated[-1] - m.evaluate(np.array([145.0]), np.array([True]))[0]) < 0.02 * stroke


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_inner_loop_closes_at_its_reversal_point(fits, model):
    """Inner loop: both common points move; coming back to the first reversal closes the loop."""
    _, y, res = fits
    st = LoopStepper(res[model].loop_model, deadband_k=0.5)
    for temp in np.linspace(30, 92, 200):
        st.step(temp)
    y_top = st.step(92.0)
    for temp in np.linspace(92, 75, 100):
        st.step(temp)
    for temp in np.linspace(75, 92, 100):
        y_back = st.step(temp)
    assert abs(y_back - y_top) < 0.01 * np.ptp(y)
    assert [p[0] for p in st.stack] == [92.0, 75.0]
    # passing the first reversal point wipes the inner loop out: back on the major branch
    y_on = st.step(100.0)
    assert st.stack == []
    major = res[model].loop_model.evaluate(np.array([100.0]), np.array([True]))[0]
    assert abs(y_on - major) < 0.01 * np.ptp(y)


def test_model2_identification_recovers_synthetic_parameters():
    cp = CommonPoints(50.0, 2.0, 110.0, 0.2)
    truth = Model2(cp, amplitude_mm=0.6, f=0.55, c11=1.2, c21=1.0, c22=0.8)
    t = np.r_[np.linspace(30, 130, 250), np.linspace(130, 30, 250)]
    heating = np.r_[np.ones(250, bool), np.zeros(250, bool)]
    y = truth.evaluate(t, heating) + np.random.default_rng(1).normal(0, 0.002, t.size)
    fit = fit_loop(t, y, "2")
    assert fit.nrmse_percent < 0.5
    p = fit.parameters
    assert p["t1_c"] == pytest.approx(50, abs=3) and p["t2_c"] == pytest.approx(110, abs=3)
    assert p["f"] == pytest.approx(0.55, abs=0.05)


def test_errors_are_defined_against_stroke(fits):
    t, y, res = fits
    fit = res["1"]
    err = fit.loop_model.evaluate(t, prepare_loop(t, y).heating) - y
    assert fit.rmse_mm == pytest.approx(np.sqrt(np.mean(err**2)))
    assert fit.nrmse_percent == pytest.approx(100 * fit.rmse_mm / np.ptp(y))
    assert fit.ard_percent == pytest.approx(100 * np.mean(np.abs(err)) / np.ptp(y))
    assert fit_loop(t, y, "1", reference_length_mm=55.0).ard_percent < fit.ard_percent


def test_bad_input_raises_fit_error():
    t = np.r_[np.linspace(30, 130, 50), np.linspace(130, 30, 50)]
    y = np.r_[np.linspace(2, 0, 50), np.linspace(0, 2, 50)]
    with pytest.raises(FitError, match="NaN"):
        fit_loop(np.where(np.arange(100) == 3, np.nan, t), y)
    with pytest.raises(FitError, match="too few"):
        fit_loop(t[:10], y[:10])
    with pytest.raises(FitError, match="not a loop"):
        fit_loop(t[:50], y[:50])  # heating only
    with pytest.raises(FitError, match="not a loop"):
        fit_loop(t, y)  # both branches on top of each other
    with pytest.raises(FitError, match="unknown model"):
        fit_loop(t, y, "nope")
    assert issubclass(FitError, ValueError)


# --------------------------------------------------------------------------- reversals, sign
REVERSAL_PATH_C = (30, 75, 72, 80, 77, 140, 100, 70, 73, 60, 63, 30)


def _reversal_path(step_k: float = 0.1) -> np.ndarray:
    pts = REVERSAL_PATH_C
    legs = zip(pts[:-1], pts[1:], strict=True)
    return np.concatenate([np.linspace(a, b, round(abs(b - a) / step_k) + 1)[1:] for a, b in legs])


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_no_jump_at_small_reversals_inside_the_transformation(fits, model):
    """Small reversals (3 K back, deadband 2.2 K) inside the transformation: the path is
    continuous; the largest step between samples is a few typical steps (before: the stepper
    retraced the old branch inside the deadband and then jumped by up to 0.55 mm, ~30×)."""
    _, y, res = fits
    seq = _reversal_path()
    path = res[model].stepper().run(seq)
    steps = np.abs(np.diff(path))
    typical = np.percentile(steps, 95)
    assert steps.max() <= 4.0 * typical, (steps.max(), typical)
    # at every reversal of the path the model turns where it was: no step above typical
    turns = np.nonzero(np.diff(np.sign(np.diff(seq))) != 0)[0] + 1
    for k in turns:
        window = steps[k : k + 30]  # the deadband's worth of samples after the turn
        assert window.max() <= 2.0 * typical, (seq[k], window.max(), typical)


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_fit_does_not_depend_on_the_sign_of_position(fits, model):
    """Fitting −y gives the mirrored model: equal nrmse and the mirrored path with reversals."""
    t, y, res = fits
    fit = res[model]
    mirrored = fit_loop(t, -y, model)
    assert mirrored.nrmse_percent == pytest.approx(fit.nrmse_percent, abs=0.1)
    seq = _reversal_path()
    a, b = fit.stepper().run(seq), mirrored.stepper().run(seq)
    assert np.max(np.abs(a + b)) < 1e-3 * np.ptp(y)


@pytest.mark.parametrize("model", CLOSED_FORM)
def test_history_run_by_run_equals_the_online_stepper(fits, model):
    """FitResult.predict evaluates run by run (vectorised); the online stepper sample by sample:
    the same memory rules give the same path, noise-made pending reversals included."""
    _, _, res = fits
    fit = res[model]
    seq = _reversal_path() + np.random.default_rng(3).normal(0.0, 0.3, _reversal_path().size)
    stepper = fit.stepper()
    stepper.reset(bool(branch_directions(seq, fit.deadband_k)[0]))
    assert np.max(np.abs(stepper.run(seq) - fit.predict(seq))) < 1e-9


def test_fitted_model_document_keeps_the_minor_branch_law(fits):
    _, _, res = fits
    fit = res["sigmoid"]
    fit.loop_model.memory_theta = 4.0
    try:
        back = fit_from_document(model_document(fit))
        seq = _reversal_path()
        assert back.loop_model.memory_theta == 4.0
        assert np.array_equal(back.predict(seq), fit.predict(seq))
    finally:
        fit.loop_model.memory_theta = 0.0


# --------------------------------------------------------------------------- reversal memory
def test_turn_detector_ignores_moves_inside_the_deadband():
    det = TurnDetector(deadband=1.0)
    assert [det.update(x) for x in (0.0, 2.0, 1.2, 2.5, 1.4)] == [False] * 4 + [True]
    assert det.turn_at == 2.5 and not det.rising and det.extreme == 1.4
    assert det.backing(1.9) and not det.backing(1.0)


def test_reversal_memory_nests_and_wipes_inner_loops():
    mem = ReversalMemory((50.0, 2.0), (100.0, 0.0))
    mem.reverse((90.0, 0.5))  # heating stopped at 90 °C: cooling from there to the low point
    assert mem.start_target() == ((90.0, 0.5), (50.0, 2.0)) and not mem.heating
    mem.reverse((70.0, 1.5))  # inner loop: heads back for the 90 °C point
    assert mem.start_target() == ((70.0, 1.5), (90.0, 0.5)) and mem.inner()
    assert mem.wipe(89.0) == 0 and mem.wipe(91.0) == 1  # passing 90 °C wipes the inner loop
    assert mem.stack == [] and mem.start_target() == ((50.0, 2.0), (100.0, 0.0))
    mem.reverse((120.0, -0.1))  # beyond the hot common point: a complete half cycle
    assert mem.stack == [] and not mem.heating


def test_reversal_memory_driven_by_position_and_of_limited_depth():
    """The controller's inverse drives the memory with the setpoint (key 1); the wire shortens on
    heating, so a heating branch wipes when the setpoint falls below its target."""
    mem = ReversalMemory((50.0, 2.0), (100.0, 0.0), key=1)
    mem.reverse((90.0, 0.5))
    mem.reverse((70.0, 1.5))  # heating again, heads for (90, 0.5)
    assert mem.wipe(0.6) == 0 and mem.wipe(0.4) == 1
    short = ReversalMemory((50.0, 2.0), (100.0, 0.0), depth=1)
    short.reverse((90.0, 0.5))
    short.reverse((70.0, 1.5))
    assert short.stack == [(70.0, 1.5)]  # the paper's moved first common point only
    assert short.start_target() == ((70.0, 1.5), (100.0, 0.0))


def test_a_history_that_starts_cold_starts_at_the_martensite_end():
    """Issue 24's demo: a recording that starts cold and first moves down a little must not start
    on the cooling branch (mid-stroke where the data never cooled that far) and then hold there
    on heating; it starts at the martensite end, whichever way the temperature moves first."""
    from smabench.physics.identify import FitResult
    from smabench.physics.loop_models import FractionBranch, SigmoidModel, starts_heating

    model = SigmoidModel(
        0.0, 0.0, -4.0, 0.0,
        FractionBranch(60.0, 2.0, 60.0, 5.0, 0.0),
        FractionBranch(40.0, 2.0, 25.0, 20.0, 0.5),  # cooling branch half done at 25 °C
        t_ref_c=25.0,
    )  # fmt: skip
    t = np.concatenate([np.linspace(25.0, 22.0, 20), np.linspace(22.0, 90.0, 200),
                        np.linspace(90.0, 22.0, 200)])  # fmt: skip
    assert starts_heating(model, 25.0) and not starts_heating(model, 90.0)
    fit = FitResult("sigmoid", {}, 0.0, 0.0, 0.0, t.size, model, deadband_k=1.0)
    y = fit.predict(t)
    assert np.all(np.abs(y[:40]) < 0.05)  # martensite up to 30 °C, not −2 mm (mid-stroke)
    heat = slice(20, 220)
    at_55 = 20 + int(np.argmin(np.abs(t[heat] - 55.0)))
    at_70 = 20 + int(np.argmin(np.abs(t[heat] - 70.0)))
    assert y[at_70] < y[at_55] - 2.0  # on heating it transforms at 60 °C, not held
