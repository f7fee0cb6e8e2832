"""nMAE and nMSE against values computed by hand."""

import numpy as np
import pytest

from nsl_hpc.studies.metrics import normalized_errors


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
