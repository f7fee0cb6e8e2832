"""Test-set error metrics on state derivatives, normalised per state by the test-set spread."""

import numpy as np


def normalized_errors(true: np.ndarray, predicted: np.ndarray) -> dict[str, float]:
    """nMAE and nMSE of ``predicted`` against ``true``, both (K, n).

    With sigma_j the standard deviation (ddof = 1) of column j of ``true``:
    nMAE = 1/(K n) sum_ij |e_ij| / sigma_j,  nMSE = 1/(K n) sum_ij (e_ij / sigma_j)^2.
    """
    scaled = (predicted - true) / true.std(axis=0, ddof=1)
    return {"nmae": float(np.abs(scaled).mean()), "nmse": float(np.square(scaled).mean())}
