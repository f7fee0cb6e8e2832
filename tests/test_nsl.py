"""Broken NSLs: envelope, margin, law and its Jacobian, recovery of known laws without hints, bad input."""

import math
import warnings

import numpy as np
import pytest

from nsl_hpc.analysis.broken_law import (
    NSLFit,
    NSLFitError,
    choose_breaks,
    log_law,
    log_law_jacobian,
    lower_envelope,
)
from nsl_hpc.nsl import backtest_nsl, default_settings, fit_nsl


def law(alpha: float, beta: float, delta0: float, *breaks: tuple[float, float, float]) -> NSLFit:
    return NSLFit(alpha, beta, delta0, list(breaks), 0.0, np.empty(0), np.empty(0))


def outcomes(true: NSLFit, seed: int, n: int = 3000, low: float = 1e3, high: float = 1e12):
    """Resources log-uniform in [low, high], errors scattered above the law (factor 1 + Exp(0.3))."""
    rng = np.random.default_rng(seed)
    r = np.exp(rng.uniform(np.log(low), np.log(high), n))
    return r, true.predict(r) * (1 + rng.exponential(0.3, n))


def test_envelope_against_hand_computed_values():
    r = np.array([1.0, 2.0, 4.0, 8.0, 3.0])
    e = np.array([0.5, 0.7, 0.2, 0.3, 0.4])
    grid, envelope = lower_envelope(r, e, 4)
    np.testing.assert_allclose(grid, [1, 2, 4, 8])
    np.testing.assert_allclose(envelope, [0.5, 0.5, 0.2, 0.2])
    grid, envelope = lower_envelope(r, e, 7)  # 1, 1.41, 2, 2.83, 4, 5.66, 8
    np.testing.assert_allclose(envelope, [0.5, 0.5, 0.5, 0.5, 0.2, 0.2, 0.2])


def test_law_formula_margin_and_jacobian():
    fit = law(0.01, 2.0, -0.5, (100.0, 0.5, -0.3))
    r = np.array([1.0, 100.0, 1e4])
    expected = 0.01 + 2.0 * r**-0.5 * (1 + (r / 100.0) ** (1 / 0.5)) ** (-0.3 * 0.5)
    np.testing.assert_allclose(fit.predict(r), expected, rtol=1e-12)
    assert fit.formula("c") == "L(c) = 0.01 + 2·c^-0.5·[1 + (c/1e+02)^(1/0.5)]^(-0.3·0.5)"
    theta, x = fit.parameters(), np.linspace(-2, 12, 40)
    numeric = np.stack([(log_law(theta + h, x) - log_law(theta - h, x)) / 2e-6
                        for h in np.eye(len(theta)) * 1e-6], axis=1)
    np.testing.assert_allclose(log_law_jacobian(theta, x), numeric, atol=1e-7)
    envelope_r, envelope_e = np.array([1.0, 10.0]), np.array([1.0, 2.0])
    fitted = NSLFit(0.0, 1.0, 0.0, [], 0.0, envelope_r, envelope_e)  # L = 1: M = (0 + ln(2)^2) / 2
    assert np.mean((np.log(fitted.predict(envelope_r)) - np.log(envelope_e)) ** 2) == pytest.approx(math.log(2)**2 / 2)


GENERATING_LAWS = {
    0: law(0.0, 5.0, -0.2),
    1: law(0.0, 5.0, -0.05, (1e6, 0.5, -0.3)),
    2: law(0.0, 5.0, -0.05, (1e5, 0.5, -0.4), (1e9, 0.5, 0.35)),
    3: law(0.0, 5.0, -0.02, (1e4, 0.3, -0.4), (1e7, 0.3, 0.3), (1e10, 0.3, -0.4)),
}


@pytest.mark.parametrize("breaks", sorted(GENERATING_LAWS))
@pytest.mark.parametrize("seed", [0, 1])
def test_known_laws_are_recovered_without_hints(breaks, seed):
    true = GENERATING_LAWS[breaks]
    r, e = outcomes(true, seed)
    fit = fit_nsl(r, e)
    true_margin = np.mean((np.log(true.predict(fit.envelope_r)) - np.log(fit.envelope_e)) ** 2)
    assert fit.b == breaks
    assert fit.fit_margin <= true_margin
    for (sigma, _, delta), (true_sigma, _, true_delta) in zip(fit.breaks, true.breaks, strict=True):
        assert abs(math.log10(sigma / true_sigma)) < 0.5 and abs(delta - true_delta) < 0.15


def test_saturating_alpha_is_recovered():
    true = law(0.002, 5.0, -0.2)
    r, e = outcomes(true, 0)
    fit = fit_nsl(r, e)
    assert fit.b == 0 and fit.alpha == pytest.approx(0.002, rel=0.3) and fit.delta0 == pytest.approx(-0.2, abs=0.05)


def test_extreme_scales_fit_without_overflow_or_nan():
    true = law(1e-8, 0.1, -0.5, (1e10, 0.5, -0.3))
    r, e = outcomes(true, 3, low=1e3, high=1e15)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_nsl(r, e)
    assert fit.b == 1 and np.isfinite(fit.margin) and fit.margin < 0.01
    assert np.all(np.isfinite(fit.predict(np.array([1.0, 1e15, 1e20]))))


def test_default_objective_beats_the_studys():
    r, e = outcomes(GENERATING_LAWS[2], 0)
    default = fit_nsl(r, e, breaks=2)
    study = fit_nsl(r, e, breaks=2, settings=default_settings(objective="study"))
    assert study.b == 2 and np.isfinite(study.margin)
    assert default.margin < study.margin


def test_fixed_breaks_and_choice_rule():
    r, e = outcomes(GENERATING_LAWS[2], 0)
    assert fit_nsl(r, e, breaks=1).b == 1 and list(fit_nsl(r, e, breaks=1).margins) == [1]
    assert choose_breaks({0: 1e-2, 1: 4e-3, 2: 3e-3}, min_gain=0.5, margin_floor=1e-4) == 1
    assert choose_breaks({0: 2e-4, 1: 5e-5}, min_gain=0.5, margin_floor=1e-4) == 0  # gain below the floor


def test_backtest_reports_extrapolation_error():
    r, e = outcomes(GENERATING_LAWS[0], 0)
    result = backtest_nsl(r, e, cut=1e7)
    assert result.fit.envelope_r.max() <= 1e7
    assert result.margin < 0.01 and 0.8 < result.final_ratio < 1.25


@pytest.mark.parametrize("resources, errors, message", [
    ([], [], "no outcomes"),
    ([5.0, 5.0, 5.0], [0.1, 0.2, 0.3], "same resource value"),
    ([1.0, 2.0], [0.1, 0.0], "error values are not finite and positive"),
    ([1.0, -2.0], [0.1, 0.2], "resource values are not finite and positive"),
    ([1.0, 2.0], [0.1, float("nan")], "not finite"),
    ([1.0, 2.0], [0.1], "2 resources but 1 errors"),
])
def test_bad_outcomes_are_refused_with_a_clear_message(resources, errors, message):
    with pytest.raises(NSLFitError, match=message):
        fit_nsl(resources, errors)
