"""nMAE and nMSE against values computed by hand."""

import numpy as np
import pytest

from nsl_hpc.studies.metrics import normalized_errors
from tests.helpers import scores_both_ways


def test_hand_computed_values():
    true = np.array([[0.0, 10.0], [2.0, 10.0], [4.0, 16.0]])  # sigma (ddof=1) = 2 and sqrt(12)
    predicted = np.array([[1.0, 10.0], [2.0, 13.0], [2.0, 16.0]])
    sigma = np.array([2.0, np.sqrt(12.0)])
    errors = np.array([[1, 0], [0, 3], [-2, 0]]) / sigma
    expected_nmae = (0.5 + 0 + 0 + 3 / np.sqrt(12) + 1 + 0) / 6
    expected_nmse = (0.25 + 0 + 0 + 9 / 12 + 1 + 0) / 6
    result = normalized_errors(true, predicted)
    assert result["nmae"] == pytest.approx(expected_nmae, rel=1e-12)
    assert result["nmse"] == pytest.approx(expected_nmse, rel=1e-12)
    assert result["nmae"] == pytest.approx(np.abs(errors).mean())


def test_perfect_prediction_scores_zero_and_is_scale_invariant():
    true = np.random.default_rng(0).normal(size=(100, 3))
    assert normalized_errors(true, true) == {"nmae": 0.0, "nmse": 0.0}
    predicted = true + 0.1
    scale = np.array([1.0, 100.0, 1e-3])
    a, b = normalized_errors(true, predicted), normalized_errors(true * scale, predicted * scale)
    assert a["nmae"] == pytest.approx(b["nmae"]) and a["nmse"] == pytest.approx(b["nmse"])


def test_the_scalar_normalisation_divides_every_column_by_one_spread_and_both_ride_in_each_row():
    true = np.array([[0.0, 10.0], [2.0, 10.0], [4.0, 16.0]])
    predicted = np.array([[1.0, 10.0], [2.0, 13.0], [2.0, 16.0]])
    sigma = np.std(true, ddof=1)  # of all six values: 5.89...
    scores = scores_both_ways(true, predicted, "scalar")
    assert scores["nmae_scalar"] == pytest.approx((1 + 3 + 2) / 6 / sigma, rel=1e-12)
    assert scores["nmse_scalar"] == pytest.approx((1 + 9 + 4) / 6 / sigma**2, rel=1e-12)
    assert scores["nmae_per_column"] == normalized_errors(true, predicted)["nmae"]
    assert (scores["nmae"], scores["nmse"]) == (scores["nmae_scalar"], scores["nmse_scalar"])
    per_column = scores_both_ways(true, predicted, "per_column")
    assert (per_column["nmae"], per_column["nmse"]) == (scores["nmae_per_column"], scores["nmse_per_column"])


def test_a_small_column_counts_less_with_the_scalar_spread():
    """The ball's case: dx/dt columns of spread 0.55, 0.32 and 4.5; an error of 10% of each column's spread
    scores 0.1 per column, and 0.067 with one spread of 2.6 (set by the large column)."""
    rng = np.random.default_rng(1)
    true = rng.normal(size=(1000, 3)) * np.array([0.55, 0.32, 4.5])
    predicted = true + 0.1 * np.array([0.55, 0.32, 4.5])
    scores = scores_both_ways(true, predicted, "scalar")
    assert scores["nmae_per_column"] == pytest.approx(0.1, rel=0.05)
    assert scores["nmae_scalar"] == pytest.approx(np.mean([0.55, 0.32, 4.5]) * 0.1 / np.std(true, ddof=1), rel=0.02)
    assert scores["nmae_scalar"] < 0.7 * scores["nmae_per_column"]
