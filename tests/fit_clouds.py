"""Outcome clouds of known broken laws and a direct multi-start fit of the margin objective (the loss of the log
residuals on Definition 1's envelope: ``nsl.above_weight``, ``nsl.huber_delta``): the reference that the fit is
held to (tests/test_nsl.py, benchmarks/fit_quality.py).

The references of the clouds tests/test_nsl.py holds the fit to take 5-60 s each; they are stored in
tests/golden/direct_objectives.json with their cloud's fingerprint, and written again by

    .venv/bin/python -m tests.fit_clouds
"""

import json
import math
from collections.abc import Callable
from dataclasses import asdict
from functools import partial
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from tqdm import tqdm

from nsl_hpc.analysis.broken_law import (
    Bounds,
    NSLFit,
    lower_envelope,
    margin_objective,
    slope_form,
    slope_form_jacobian,
    theta_of,
    weighted_residuals,
)
from nsl_hpc.analysis.published import published_laws
from nsl_hpc.core.atomic import replacing
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


def direct_objective(r: np.ndarray, e: np.ndarray, b: int, starts: int = 60, K: int = 100,
                     envelope: str = "step") -> float:
    """The reference: the least margin objective (``objective_of``, conf/nsl's loss) of a law in the fit's box
    (slopes in [-max_slope, max_rise]: a law that does not rise) that bounded robust least squares of ln L on the
    envelope reaches from ``starts`` random starts (no structured starts, a long budget)."""
    settings = default_settings()
    loss = settings.margin_loss
    grid, envelope_e = lower_envelope(r, e, K, envelope)
    x, y = np.log(grid), np.log(envelope_e)
    middle = (x[0] + x[-1]) / 2
    x = x - middle
    bounds = Bounds.for_grid(x, y, b, settings)
    rng = np.random.default_rng(0)
    best = math.inf

    def residuals(u: np.ndarray) -> np.ndarray:
        return weighted_residuals(theta_of(u), x, y, loss.above_weight)[0]

    def jacobian(u: np.ndarray) -> np.ndarray:
        return slope_form_jacobian(u, x) * weighted_residuals(theta_of(u), x, y, loss.above_weight)[1][:, None]

    for _ in range(starts):
        theta = rng.uniform(bounds.lower, np.minimum(bounds.upper, bounds.lower + 40))
        theta[0] = y.min() + np.log(rng.uniform(0.3, 1.0)) if rng.random() < 0.5 else bounds.lower[0]
        theta[2], theta[5::3], theta[4::3] = rng.uniform(-2, 1), rng.uniform(-4, 4, b), rng.uniform(0.2, 1, b)
        theta[3::3] = np.sort(theta[3::3])
        theta[1] = y[0] - theta[2] * x[0]
        result = least_squares(residuals, bounds.clip(slope_form(theta)), bounds=(bounds.lower, bounds.upper),
                               jac=jacobian, x_scale="jac", max_nfev=400, **loss.least_squares_loss())
        best = min(best, margin_objective(theta_of(result.x), x, y, loss))
    return best


def objective_of(fit: NSLFit, r: np.ndarray, e: np.ndarray, K: int = 100) -> float:
    """The margin objective of ``fit`` on Definition 1's envelope of the outcomes (r, e) (conf/nsl's loss; the
    plain one: the fit's M)."""
    grid, envelope_e = lower_envelope(r, e, K)
    with np.errstate(divide="ignore"):  # ln alpha = -inf for a law without alpha
        theta = fit.parameters()
    return margin_objective(theta, np.log(grid), np.log(envelope_e), default_settings().margin_loss)


def outcomes(true: NSLFit, seed: int, n: int = 3000, low: float = 1e3, high: float = 1e12):
    """Resources log-uniform in [low, high], errors scattered above the law (factor 1 + Exp(0.3))."""
    rng = np.random.default_rng(seed)
    r = np.exp(rng.uniform(np.log(low), np.log(high), n))
    return r, true.predict(r) * (1 + rng.exponential(0.3, n))


def shape(delta0: float, *breaks: tuple[float, float, float], low: float) -> NSLFit:
    """A law with these slopes and breaks that starts at error 10 at ``low``."""
    unit = law(0.0, 1.0, delta0, *breaks)
    return law(0.0, 10 / float(unit.predict(low)), delta0, *breaks)


DIP, DROP = 10**0.1, 10**0.2
HARD_SHAPES = {  # name: (law, smallest and largest resource, outcomes); errors stay in [1e-6, 10]
    "b0": (shape(-0.5, low=1e2), 1e2, 1e8, 300),
    "b1 to slope -5": (shape(-0.1, (1e4, 0.2, -4.9), low=1e2), 1e2, 10**5.2, 3000),
    "steep start, slope change +5": (shape(-4.0, (10**3.5, 0.2, 3.8), low=1e2), 1e2, 1e8, 3000),
    "dip: breaks 0.1 decades apart": (shape(-0.3, (1e5, 0.2, -3.0), (1e5 * DIP, 0.2, 3.0), low=1e2), 1e2, 1e9, 3000),
    "drop: breaks 0.2 decades apart": (shape(-0.3, (1e5, 0.2, -2.7), (1e5 * DROP, 0.2, 2.7), low=1e2), 1e2, 1e9, 300),
    "plateau then steep fall": (shape(0.0, (1e5, 0.2, -5.0), (1e6, 0.2, 4.5), low=1e2), 1e2, 1e10, 30000),
    "b3": (shape(-0.02, (1e4, 0.3, -0.4), (1e7, 0.3, 0.3), (1e10, 0.3, -0.4), low=1e2), 1e2, 1e12, 3000),
    "b4": (shape(-0.2, (1e4, 0.2, -0.8), (1e6, 0.2, 0.6), (1e8, 0.2, -1.0), (1e10, 0.2, 0.8), low=1e2),
           1e2, 1e11, 30000),
}


SWEEP_LIKE = {name: shape for name, shape in (published_shapes() | random_shapes(8, seed=1)).items()
              if name.startswith(("wiener_hammerstein/narx", "motor", "ball/input_affine/compute/nmse",
                                  "ball/port_hamiltonian", "silverbox/subnet", "random 3", "random 6", "random 7"))}


def hard_cloud(name: str) -> tuple[NSLFit, np.ndarray, np.ndarray]:
    """The law of HARD_SHAPES[name] and its outcomes."""
    true, low, high, n = HARD_SHAPES[name]
    return (true, *outcomes(true, 0, n, low, high))


def sweep_like_cloud(name: str) -> tuple[NSLFit, np.ndarray, np.ndarray]:
    """The law of SWEEP_LIKE[name] and a sweep's 7,056 outcomes of it."""
    true, low, high = SWEEP_LIKE[name]
    return (true, *cloud(true, low, high, 7056, seed=list(SWEEP_LIKE).index(name)))


REFERENCES = Path(__file__).parent / "golden" / "direct_objectives.json"
# key -> (the law and its cloud, the direct fit's random starts)
REFERENCE_CLOUDS: dict[str, tuple[Callable[[], tuple[NSLFit, np.ndarray, np.ndarray]], int]] = {
    **{f"hard: {name}": (partial(hard_cloud, name), 20) for name in HARD_SHAPES},
    **{f"sweep-like: {name}": (partial(sweep_like_cloud, name), 60) for name in SWEEP_LIKE},
}


def fingerprint(r: np.ndarray, e: np.ndarray) -> list[float]:
    """What tells one cloud from another: its size and the sums of ln r and ln e."""
    return [len(r), float(np.log(r).sum()), float(np.log(e).sum())]


def stored_direct_objective(key: str, r: np.ndarray, e: np.ndarray) -> float:
    """``direct_objective`` of the cloud REFERENCE_CLOUDS[key], as stored; an AssertionError if (r, e) is not the
    cloud it was computed on, or conf/nsl's loss not the one it was computed with."""
    stored = json.loads(REFERENCES.read_text()).get(key)
    loss = asdict(default_settings().margin_loss)
    assert stored is not None and np.allclose(stored["cloud"], fingerprint(r, e), rtol=1e-9, atol=0) and (
        stored["loss"] == loss), (f"no stored direct objective of this cloud of {key!r} with the loss {loss}: write "
                                  "them again with python -m tests.fit_clouds")
    return stored["objective"]


def direct_reference(key: str) -> dict:
    """The direct fit of cloud ``key`` with the true b, as stored in REFERENCES."""
    make, starts = REFERENCE_CLOUDS[key]
    true, r, e = make()
    return {"b": true.b, "starts": starts, "cloud": fingerprint(r, e), "loss": asdict(default_settings().margin_loss),
            "objective": direct_objective(r, e, true.b, starts)}


def main() -> None:
    """Write REFERENCES (a few minutes)."""
    references = {key: direct_reference(key) for key in tqdm(REFERENCE_CLOUDS, desc="direct fits", unit="cloud")}
    with replacing(REFERENCES) as temporary:
        temporary.write_text(json.dumps(references, indent=1) + "\n")


if __name__ == "__main__":
    main()
