"""How sure a fitted law is: refit it on resampled outcomes and read intervals off the refits.

A replicate draws the outcomes (tasks), rebuilds the lower envelope from the draw and refines the fitted law on it
(same b, started from the fit: the intervals are conditional on b). Quantiles of the replicates give the
intervals of the last slope, the break positions, alpha and L at the largest observed resource and ten times
beyond it: ``basic`` intervals by default (``nsl.bootstrap_interval``), the quantiles reflected about the fit's
value, since the replicates are biased: a resample's envelope is sparser than the fit's, so it, and the law on
it, lies higher; ``percentile`` ones are the quantiles themselves.

A replicate holds half of the outcomes, drawn without replacement, by default (``nsl.bootstrap_draw: half``;
``replacement``: as many drawn with replacement, about 63% of them distinct). Where the best of n outcomes lie
on the law the envelope bounds, the envelope lies above it by steps that shrink as 1 / n, and the fit with them;
half as many outcomes double that excess, so the half-samples' excess over the fit equals the fit's over the law
and the basic interval takes all of it away (a with-replacement resample takes away 1 / 0.63 - 1 = 58% of it);
for a quantity that varies as 1 / sqrt(n), the half-samples' spread about the fit is the fit's about the truth
(variance 1 / m - 1 / n = 1 / n at m = n / 2). docs/fits.md measures both draws on planted laws.
"""

from collections.abc import Mapping
from typing import Any

import numpy as np

from nsl_hpc.analysis.broken_law import FitSettings, NSLFit, log_law, refit


def bootstrap_thetas(fit: NSLFit, resources: np.ndarray, errors: np.ndarray, replicates: int, seed: int, K: int,
                     settings: FitSettings, draw: str) -> np.ndarray:
    """(replicates, 3 + 3 b): theta = [ln alpha, ln beta, delta0, (ln sigma_i, phi_i, delta_i)...] of each refit
    on a draw of the n outcomes (``draw``: ``half``, ceil(n / 2) of them without replacement; ``replacement``, n
    with replacement)."""
    rng = np.random.default_rng(seed)
    n = len(resources)
    thetas = []
    for _ in range(replicates):
        drawn = rng.choice(n, (n + 1) // 2, replace=False) if draw == "half" else rng.integers(0, n, n)
        thetas.append(refit(fit, resources[drawn], errors[drawn], K, settings))
    return np.array(thetas).reshape(replicates, 3 + 3 * fit.b)


def last_slope(theta: np.ndarray) -> np.ndarray:
    """delta0 + sum_i delta_i of theta (..., 3 + 3 b): the log-log slope of the law's power part beyond its
    last break."""
    return theta[..., 2] + theta[..., 5::3].sum(axis=-1)


def law_values(thetas: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(replicates, len(r)): L(r) of every theta."""
    x = np.log(np.asarray(r, dtype=float))
    return np.exp(np.stack([log_law(theta, x) for theta in thetas]))


def interval(point: np.ndarray | float, sample: np.ndarray, level: float, kind: str, log: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
    """The ``level`` interval (low, high) of a quantity of value ``point`` from its replicates ``sample``
    (replicates on axis 0): ``percentile``: the sample's quantiles q; ``basic``: 2 point - q (each bound the
    other quantile reflected about the point), on a log scale for a positive quantity (``log``)."""
    tail = (1 - level) / 2
    if log:
        point, sample = np.log(point), np.log(sample)
    low, high = np.quantile(sample, [tail, 1 - tail], axis=0)
    if kind == "basic":
        low, high = 2 * np.asarray(point) - high, 2 * np.asarray(point) - low
    return (np.exp(low), np.exp(high)) if log else (low, high)


def intervals(fit: NSLFit, thetas: np.ndarray, largest: float, level: float, kind: str) -> dict[str, Any]:
    """The fit's point values and ``level`` intervals of ``kind`` (``<name>_lo``, ``<name>_hi``) of last_slope,
    sigma_i, alpha (percentile: alpha is often 0), L_at_max (L at the ``largest`` observed resource) and L_at_10x
    (at 10 x largest)."""
    point = fit.parameters()
    found: dict[str, Any] = {"last_slope": float(last_slope(point)), "L_at_max": float(fit.predict(largest)),
                              "L_at_10x": float(fit.predict(10 * largest))}
    at = law_values(thetas, np.array([largest, 10 * largest])).T
    quantities = {"last_slope": (found["last_slope"], last_slope(thetas), kind, False),
                  "alpha": (fit.alpha, np.exp(thetas[:, 0]), "percentile", False),
                  "L_at_max": (found["L_at_max"], at[0], kind, True),
                  "L_at_10x": (found["L_at_10x"], at[1], kind, True)}
    quantities |= {f"sigma_{i}": (sigma, np.exp(thetas[:, 3 * i]), kind, True)
                   for i, (sigma, _, _) in enumerate(fit.breaks, start=1)}
    for name, (value, sample, form, log) in quantities.items():
        low, high = interval(value, sample, level, form, log)
        found |= {f"{name}_lo": float(low), f"{name}_hi": float(high)}
    return found


def band(fit: NSLFit, thetas: np.ndarray, r: np.ndarray, level: float, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Pointwise ``level`` band (low, high) of ``kind`` of the law ``fit`` over the resources ``r``."""
    return interval(fit.predict(r), law_values(thetas, r), level, kind, log=True)


def thetas_of(row: Mapping[str, Any]) -> np.ndarray:
    """The bootstrap thetas an nsl_fits row holds, (replicates, 3 + 3 b) (0 rows when none)."""
    stored = row.get("bootstrap_thetas") or []
    return np.array([list(theta) for theta in stored], dtype=float).reshape(len(stored), 3 + 3 * (row["b"] or 0))
