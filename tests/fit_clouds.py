"""Outcome clouds of known broken laws and a direct multi-start fit of Definition 1's margin: the reference
that the fit is held to (tests/test_nsl.py, benchmarks/fit_quality.py)."""

import math

import numpy as np
from scipy.optimize import least_squares

from nsl_hpc.analysis.broken_law import (
    Bounds,
    NSLFit,
    log_law,
    lower_envelope,
    slope_form,
    slope_form_jacobian,
    theta_of,
)
from nsl_hpc.analysis.published import published_laws
from nsl_hpc.nsl import default_settings


def law(alpha: float, beta: float, delta0: float, *breaks: tuple[float, float, float]) -> NSLFit:
    return NSLFit(alpha, beta, delta0, list(breaks), 0.0, np.empty(0), np.empty(0))


def cloud(true: NSLFit, low: float, high: float, n: int, seed: int, scatter: float = 0.15
          ) -> tuple[np.ndarray, np.ndarray]:
    """n outcomes, resources log-uniform in [low, high]; errors as a sweep's: the law times a log-normal
    spread (``scatter``, natural-log sd: how far the best models fall from the law) for a fifth of them, the
    rest also under-trained or too small (a further factor exp(Exp(1)))."""
    rng = np.random.default_rng(seed)
    r = np.exp(rng.uniform(np.log(low), np.log(high), n))
    log_factor = scatter * rng.standard_normal(n) + np.where(rng.random(n) < 0.2, 0.0, rng.exponential(1.0, n))
    return r, true.predict(r) * np.exp(log_factor)


def published_shapes() -> dict[str, tuple[NSLFit, float, float]]:
    """The paper's ten laws over their grids' resource ranges: name -> (law, low, high)."""
    return {"/".join(key): (entry.law, *entry.resource_range) for key, entry in published_laws().items()}


def random_shapes(count: int, seed: int) -> dict[str, tuple[NSLFit, float, float]]:
    """``count`` laws in the published style over 4-8 decades: 1-4 breaks at phi 0.2, the first two a close
    pair (a drop of slope -1.5 to -5 and a flattening 0.1-1 decade later), then a steepening and a flattening
    by 0.4-1 each in the upper half of the range."""
    rng = np.random.default_rng(seed)
    shapes = {}
    for k in range(count):
        b = 1 + k % 4
        low = 10 ** rng.uniform(1, 6)
        decades = rng.uniform(4, 8)
        first = low * 10 ** (decades * rng.uniform(0.15, 0.35))
        drop = rng.uniform(-5, -1.5)
        positions = [first, first * 10 ** rng.uniform(0.1, 1.0)][:b]
        later = b - len(positions)
        positions += list(low * 10 ** (decades * (np.linspace(0.55, 0.9, later) + rng.uniform(-0.03, 0.03, later))))
        slopes = [drop, -drop * rng.uniform(0.7, 1.0)][:b]
        slopes += [sign * rng.uniform(0.4, 1.0) for sign in (-1, 1)[:later]]
        delta0 = rng.uniform(-0.3, 0.0)
        unit = law(0.0, 1.0, delta0, *((float(s), 0.2, float(d)) for s, d in zip(positions, slopes, strict=True)))
        beta = float(rng.uniform(0.3, 3.0) / unit.predict(low))
        shapes[f"random {k} (b = {b})"] = (law(0.0, beta, delta0, *unit.breaks), low, low * 10**decades)
    return shapes


def b_acceptable(chosen: int, true: int) -> bool:
    """The choice of b asked of the fit: within 1 of the true b, and no extra break on a 0- or 1-break law."""
    return chosen <= true if true <= 1 else abs(chosen - true) <= 1


def direct_margin(r: np.ndarray, e: np.ndarray, b: int, starts: int = 60, K: int = 100,
                  envelope: str = "step") -> float:
    """The reference: the least Definition-1 margin of a law in the fit's box (slopes in [-max_slope, max_rise]:
    a law that does not rise) that bounded least squares of ln L on the envelope reaches from ``starts`` random
    starts (no structured starts, a long budget)."""
    settings = default_settings()
    grid, envelope_e = lower_envelope(r, e, K, envelope)
    x, y = np.log(grid), np.log(envelope_e)
    middle = (x[0] + x[-1]) / 2
    x = x - middle
    bounds = Bounds.for_grid(x, y, b, settings)
    rng = np.random.default_rng(0)
    best = math.inf
    for _ in range(starts):
        theta = rng.uniform(bounds.lower, np.minimum(bounds.upper, bounds.lower + 40))
        theta[0] = y.min() + np.log(rng.uniform(0.3, 1.0)) if rng.random() < 0.5 else bounds.lower[0]
        theta[2], theta[5::3], theta[4::3] = rng.uniform(-2, 1), rng.uniform(-4, 4, b), rng.uniform(0.2, 1, b)
        theta[3::3] = np.sort(theta[3::3])
        theta[1] = y[0] - theta[2] * x[0]
        result = least_squares(lambda u: log_law(theta_of(u), x) - y, bounds.clip(slope_form(theta)),
                               bounds=(bounds.lower, bounds.upper), jac=lambda u: slope_form_jacobian(u, x),
                               x_scale="jac", max_nfev=400)
        best = min(best, float(np.mean(result.fun**2)))
    return best
