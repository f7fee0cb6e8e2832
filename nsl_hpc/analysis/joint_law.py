"""A joint law of the error over model size, data and training length (Chinchilla's parametric form):

    L(p, d, n) = E + A p^-alpha + B d^-beta + C n^-gamma

p: parameters, d: training points, n: the study's training length (epochs; iterations per point). Fitted on the
best outcome over the seeds of each grid configuration (the envelope side: a bad seed says nothing of what the
configuration can reach), by robust least squares (Huber) on the log residuals from a grid of starts, as
Hoffmann et al. (2022) fit theirs, a law above an outcome weighing ``above_weight`` times one below it (the law
bounds from below what the sizes reach, as Section 4.3's loss weighs it). A variable with fewer than
``min_levels`` distinct values among the configurations has no term (its exponent cannot be told apart from its
coefficient). Settings: ``nsl.joint``.
"""

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from nsl_hpc.analysis.nsl_settings import Joint

VARIABLES = ("model", "data", "length")  # the order of a law's terms and of the columns of ``sizes``


class JointLawError(ValueError):
    """Too few configurations to fit a joint law."""


@dataclass(frozen=True)
class JointLaw:
    """``theta`` = [ln E, (ln A, alpha), ...] for the terms of ``variables`` (a subset of VARIABLES, in order);
    ``loss``: the fit's mean Huber loss of the log residuals."""

    variables: tuple[str, ...]
    theta: np.ndarray
    loss: float

    def log_predict(self, sizes: Mapping[str, np.ndarray]) -> np.ndarray:
        """ln L at ``sizes`` (each variable: an array of one shape)."""
        return log_law(self.theta, columns(sizes, self.variables))

    def formula(self) -> str:
        symbol = {"model": "p", "data": "d", "length": "n"}
        terms = [f"{np.exp(self.theta[0]):.3g}"] + [
            f"{np.exp(self.theta[1 + 2 * i]):.3g} {symbol[name]}^-{self.theta[2 + 2 * i]:.3g}"
            for i, name in enumerate(self.variables)]
        return "L = " + " + ".join(terms)


def columns(sizes: Mapping[str, np.ndarray], variables: Sequence[str]) -> np.ndarray:
    """(terms, ...) ln of the ``variables`` of ``sizes``."""
    return np.log(np.stack([np.asarray(sizes[name], dtype=float) for name in variables]))


def log_law(theta: np.ndarray, log_sizes: np.ndarray) -> np.ndarray:
    """ln L (shape of log_sizes[0]) of theta at the ln sizes (terms, ...)."""
    logs = term_logs(theta, log_sizes)
    top = logs.max(axis=0)
    return top + np.log(np.exp(logs - top).sum(axis=0))


def term_logs(theta: np.ndarray, log_sizes: np.ndarray) -> np.ndarray:
    """(1 + terms, ...) ln of each term: ln E, ln A - alpha ln p, ..."""
    constant = np.full(log_sizes.shape[1:], theta[0])
    return np.stack([constant, *(theta[1 + 2 * i] - theta[2 + 2 * i] * log_sizes[i] for i in range(len(log_sizes)))])


def jacobian(theta: np.ndarray, log_sizes: np.ndarray) -> np.ndarray:
    """(points, len(theta)) d ln L / d theta."""
    logs = term_logs(theta, log_sizes)
    weights = np.exp(logs - logs.max(axis=0))
    weights /= weights.sum(axis=0)  # each term's share of L
    parts = [weights[0]]
    for i in range(len(log_sizes)):
        parts += [weights[1 + i], -weights[1 + i] * log_sizes[i]]
    return np.stack(parts, axis=1)


def fit_from(start: np.ndarray, log_sizes: np.ndarray, log_errors: np.ndarray, settings: Joint
             ) -> tuple[np.ndarray, float]:
    """(theta, mean Huber loss) refined from ``start``. Exponents lie in [0, max_exponent]; E and each term at the
    smallest size at least ``floor_share`` of the smallest error (below that they change no prediction in the
    sweep's range, and a vanishing term would drift without end). Fitted with each size over its smallest."""
    terms, origin = len(log_sizes), log_sizes.min(axis=1)
    floor = log_errors.min() + np.log(settings.floor_share)
    low = np.array([floor] + [floor, 0.0] * terms)
    high = np.array([log_errors.max()] + [np.inf, settings.max_exponent] * terms)
    shifted = log_sizes - origin[:, None]

    def weights(theta: np.ndarray) -> np.ndarray:  # (points,) a law above an outcome weighs above_weight
        return np.where(log_law(theta, shifted) > log_errors, settings.above_weight, 1.0)

    result = least_squares(lambda theta: weights(theta) * (log_law(theta, shifted) - log_errors),
                           np.clip(moved(start, origin, -1), low, high),
                           jac=lambda theta: weights(theta)[:, None] * jacobian(theta, shifted),
                           bounds=(low, high), loss="huber", f_scale=settings.huber_delta,
                           max_nfev=settings.max_evaluations, ftol=settings.tolerance, xtol=settings.tolerance)
    return moved(result.x, origin, 1), float(2 * result.cost / len(log_errors))


def moved(theta: np.ndarray, origin: np.ndarray, sign: int) -> np.ndarray:
    """theta with each term's ln coefficient for sizes over ``origin`` (ln) (sign -1) or back (sign 1)."""
    out = theta.copy()
    out[1::2] += sign * theta[2::2] * origin
    return out


def starts(log_sizes: np.ndarray, log_errors: np.ndarray, exponents: Sequence[float]) -> list[np.ndarray]:
    """Every combination of the start ``exponents`` over the terms, each term worth the median error at the
    median size and E half the smallest error."""
    middle = np.median(log_sizes, axis=1)
    typical, floor = float(np.median(log_errors)), float(log_errors.min() + np.log(0.5))
    return [np.array([floor, *itertools.chain.from_iterable((typical + power * middle[i], power)
                                                            for i, power in enumerate(powers))])
            for powers in itertools.product(exponents, repeat=len(log_sizes))]


def fitted_variables(sizes: Mapping[str, np.ndarray], min_levels: int) -> tuple[str, ...]:
    """The VARIABLES with at least ``min_levels`` distinct values in ``sizes``."""
    return tuple(name for name in VARIABLES if len(np.unique(sizes[name])) >= min_levels)


def fit_joint_law(sizes: Mapping[str, np.ndarray], errors: np.ndarray, settings: Joint) -> JointLaw:
    """The joint law of ``errors`` (configurations,) at ``sizes`` (VARIABLES -> (configurations,)), the best of the
    refinements from ``starts`` (``settings``: nsl.joint)."""
    variables = fitted_variables(sizes, settings.min_levels)
    if not variables or len(errors) < settings.min_configurations:
        raise JointLawError(f"{len(errors)} configurations with {len(variables)} varied sizes: a joint law needs "
                            f"{settings.min_configurations} (nsl.joint.min_configurations) and one size with "
                            f"{settings.min_levels} values (nsl.joint.min_levels)")
    log_sizes, log_errors = columns(sizes, variables), np.log(errors)
    fits = [fit_from(start, log_sizes, log_errors, settings)
            for start in starts(log_sizes, log_errors, settings.start_exponents)]
    theta, loss = min(fits, key=lambda fit: fit[1])
    return JointLaw(variables, theta, loss)


def bootstrap_joint_laws(law: JointLaw, sizes: Mapping[str, np.ndarray], errors: np.ndarray, replicates: int,
                         seed: int, settings: Joint) -> list[JointLaw]:
    """``law`` refitted, from itself, on ``replicates`` resamples of the configurations (with replacement)."""
    rng = np.random.default_rng(seed)
    log_sizes, log_errors = columns(sizes, law.variables), np.log(errors)
    laws = []
    for _ in range(replicates):
        drawn = rng.integers(0, len(errors), len(errors))
        theta, loss = fit_from(law.theta, log_sizes[:, drawn], log_errors[drawn], settings)
        laws.append(JointLaw(law.variables, theta, loss))
    return laws
