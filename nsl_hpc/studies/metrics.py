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
    sums = ErrorSums(spreads(true))
    sums.add(predicted - true)
    return sums.normalized(normalization)


def spreads(true: np.ndarray) -> dict[str, np.ndarray]:
    """s_j (n,) of each normalisation for the targets ``true`` (K, n): sigma_j per column, or sigma of all."""
    return {"per_column": true.std(axis=0, ddof=1), "scalar": np.full(true.shape[1], true.std(ddof=1))}


class ErrorSums:
    """Per-column sums of |e| and e^2 of one model, added chunk by chunk of samples, so that a large test set is
    scored without holding every prediction; ``spreads`` are those of the whole test set (``spreads``)."""

    def __init__(self, spreads: Mapping[str, np.ndarray]):
        self.spreads = spreads
        self.absolute = np.zeros(len(spreads["scalar"]))
        self.squared = np.zeros(len(spreads["scalar"]))
        self.count = 0

    def add(self, error: np.ndarray) -> None:
        """Count the errors (k, n) of k more samples."""
        self.absolute += np.abs(error).sum(axis=0)
        self.squared += np.square(error).sum(axis=0)
        self.count += len(error)

    def normalized(self, normalization: str) -> dict[str, float]:
        """nMAE and nMSE over every sample added (normalized_errors' formula)."""
        spread = self.spreads[normalization]
        values = self.count * len(spread)
        return {"nmae": float((self.absolute / spread).sum() / values),
                "nmse": float((self.squared / np.square(spread)).sum() / values)}

    def both_ways(self, normalization: str) -> dict[str, float]:
        """The row's scores: both normalisations, and nmae / nmse as ``normalization`` selects."""
        scores = {f"{name}_{way}": value for way in NORMALIZATIONS
                  for name, value in self.normalized(way).items()}
        return {**scores, **selected(scores, normalization)}


def selected(scores: Mapping[str, float], normalization: str) -> dict[str, float]:
    return {name: scores[f"{name}_{normalization}"] for name in ("nmae", "nmse")}
