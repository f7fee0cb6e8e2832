"""Test-set error metrics on state derivatives (or outputs), normalised by the test-set spread."""

from collections.abc import Mapping

import numpy as np

# per_column: the paper's formula, each column j divided by its own spread sigma_j; scalar: the authors' code
# (utils.normalized_mae / normalized_mse), every column divided by one spread of the whole target matrix.
NORMALIZATIONS = ("per_column", "scalar")


def normalized_errors(true: np.ndarray, predicted: np.ndarray, normalization: str = "per_column"
                      ) -> dict[str, float]:
    """nMAE and nMSE of ``predicted`` against ``true``, both (K, n): with s_j = sigma_j, the standard deviation
    (ddof = 1) of column j of ``true`` (per_column), or s_j = sigma, that of all of ``true`` (scalar),
    nMAE = 1/(K n) sum_ij |e_ij| / s_j and nMSE = 1/(K n) sum_ij (e_ij / s_j)^2."""
    spread = true.std(axis=0, ddof=1) if normalization == "per_column" else true.std(ddof=1)
    scaled = (predicted - true) / spread
    return {"nmae": float(np.abs(scaled).mean()), "nmse": float(np.square(scaled).mean())}


def scores_both_ways(true: np.ndarray, predicted: np.ndarray, normalization: str) -> dict[str, float]:
    """nmae_per_column, nmse_per_column, nmae_scalar, nmse_scalar, and nmae / nmse: the pair ``normalization``
    selects (``metric.normalization``)."""
    scores = {f"{name}_{way}": value for way in NORMALIZATIONS
              for name, value in normalized_errors(true, predicted, way).items()}
    return {**scores, **selected(scores, normalization)}


def selected(scores: Mapping[str, float], normalization: str) -> dict[str, float]:
    return {name: scores[f"{name}_{normalization}"] for name in ("nmae", "nmse")}
