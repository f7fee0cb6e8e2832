"""Broken neural scaling laws (Definition 1 of the study), fitted without a hand-made initial guess.

For outcomes (r_i, e_i) (r: compute, data or parameters; e: nMAE or nMSE):

- lower envelope E(r) = min{e_i : r_i <= r}, sampled at K log-spaced resources r~_k from min r to max r;
- law L(r) = alpha + beta r^delta0 prod_i [1 + (r / sigma_i)^(1 / phi_i)]^(delta_i phi_i),
  alpha, beta >= 0, sigma_i > 0, phi_i >= phi_min (conf/nsl/default.yaml);
- margin M = mean_k (ln L(r~_k) - ln E(r~_k))^2 (natural logarithms).

Everything is evaluated in log space, ln L = logaddexp(ln alpha, ln beta + delta0 x
+ sum_i delta_i phi_i softplus((x - ln sigma_i) / phi_i)) with x = ln r, so resources up to 1e15 and errors
down to 1e-8 neither overflow nor underflow. The law is piecewise linear in log-log space with smooth
corners: the fit starts from piecewise-linear least-squares fits of the envelope with corners at every
combination of candidate positions on the log grid, refines the best few with bounded least squares on the
log residuals (which minimises M directly), and picks the number of breaks b by a penalised margin.
"""

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from scipy.optimize import least_squares
from scipy.special import expit

OBJECTIVES = ("margin", "study")


class NSLFitError(ValueError):
    """Outcomes that cannot be fitted (empty, a single resource value, non-positive or NaN values)."""


@dataclass(frozen=True)
class NSLFit:
    """A fitted law; ``breaks`` holds (sigma, phi, delta) per break, ``envelope_r`` / ``envelope_e`` the K
    envelope points it was fitted to and ``margins`` the best margin found for each number of breaks tried."""

    alpha: float
    beta: float
    delta0: float
    breaks: list[tuple[float, float, float]]
    margin: float
    envelope_r: np.ndarray = field(repr=False)
    envelope_e: np.ndarray = field(repr=False)
    margins: dict[int, float] = field(default_factory=dict)
    objective: str = "margin"

    @property
    def b(self) -> int:
        return len(self.breaks)

    def predict(self, r: np.ndarray | float) -> np.ndarray:
        """L(r) for resources ``r`` (any shape)."""
        return np.exp(log_law(self.parameters(), np.log(np.asarray(r, dtype=float))))

    def parameters(self) -> np.ndarray:
        """[ln alpha, ln beta, delta0, (ln sigma_i, phi_i, delta_i) ...]."""
        with np.errstate(divide="ignore"):
            head = [np.log(self.alpha), np.log(self.beta), self.delta0]
        return np.array(head + [v for s, p, d in self.breaks for v in (np.log(s), p, d)])

    def formula(self, symbol: str = "r") -> str:
        """The law in the study's notation, 2 significant digits."""
        terms = [] if self.alpha == 0 else [f"{self.alpha:.2g} + "]
        terms.append(f"{self.beta:.2g}·{symbol}^{self.delta0:.2g}")
        for sigma, phi, delta in self.breaks:
            terms.append(f"·[1 + ({symbol}/{sigma:.2g})^(1/{phi:.2g})]^({delta:.2g}·{phi:.2g})")
        return f"L({symbol}) = " + "".join(terms)


def lower_envelope(resources: np.ndarray, errors: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray]:
    """(r~, e~): ``points`` log-spaced resources from the smallest to the largest, and the smallest error of
    the outcomes with a resource at most r~_k."""
    order = np.argsort(resources, kind="stable")
    sorted_r, running_min = resources[order], np.minimum.accumulate(errors[order])
    grid = np.geomspace(sorted_r[0], sorted_r[-1], points)
    grid[0], grid[-1] = sorted_r[0], sorted_r[-1]
    return grid, running_min[np.searchsorted(sorted_r, grid, side="right") - 1]


def softplus(z: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, z)


def log_law(theta: np.ndarray, x: np.ndarray) -> np.ndarray:
    """ln L at x = ln r for theta = [ln alpha, ln beta, delta0, (ln sigma_i, phi_i, delta_i) ...]."""
    return np.logaddexp(theta[0], log_power(theta, x))


def log_power(theta: np.ndarray, x: np.ndarray) -> np.ndarray:
    """ln of the law without alpha."""
    y = theta[1] + theta[2] * x
    for log_sigma, phi, delta in theta[3:].reshape(-1, 3):
        y = y + delta * phi * softplus((x - log_sigma) / phi)
    return y


def log_law_jacobian(theta: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d ln L / d theta, shape (len(x), len(theta))."""
    y = log_power(theta, x)
    w = expit(y - theta[0])  # share of the power term in L
    columns = [1 - w, w, w * x]
    for log_sigma, phi, delta in theta[3:].reshape(-1, 3):
        z = (x - log_sigma) / phi
        columns += [-w * delta * expit(z), w * delta * (softplus(z) - z * expit(z)), w * phi * softplus(z)]
    return np.stack(columns, axis=1)


def margin_of(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray) -> float:
    return float(np.mean((log_law(theta, x) - log_e) ** 2))


@dataclass(frozen=True)
class Bounds:
    """Box bounds of theta for b breaks on the log grid ``x`` with log errors ``log_e``."""

    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def for_grid(cls, x: np.ndarray, log_e: np.ndarray, b: int, max_slope: float, edge: float,
                 phi_min: float) -> "Bounds":
        """Breaks stay ``edge`` of the log range inside it: a corner at the very end of the data is not
        identifiable (it fits the scatter of the few outcomes that make the envelope there)."""
        span = max(x[-1] - x[0], phi_min)
        lower = [log_e.min() - 30, log_e.min() - 30 - max_slope * np.abs(x).max(), -max_slope]
        upper = [log_e.max(), log_e.max() + 30 + max_slope * np.abs(x).max(), max_slope]
        lower += [x[0] + edge * span, phi_min, -max_slope] * b
        upper += [x[-1] - edge * span, max(span, phi_min * 1.01), max_slope] * b
        return cls(np.array(lower, dtype=float), np.array(upper, dtype=float))

    def clip(self, theta: np.ndarray) -> np.ndarray:
        return np.clip(theta, self.lower, self.upper)


def piecewise_linear_starts(x: np.ndarray, log_e: np.ndarray, b: int, positions: int, alpha_share: float,
                            phi_min: float) -> list[tuple[float, np.ndarray]]:
    """Initial thetas from least-squares piecewise-linear fits of ln(e~ - alpha) with corners at every
    combination of b of ``positions`` evenly spaced inner points of the log grid, with alpha = 0 and
    alpha = ``alpha_share`` * min e~; returned with their squared error, best first."""
    span = x[-1] - x[0]
    phi = max(phi_min, 0.03 * span)
    corners = x[0] + span * np.arange(1, positions + 1) / (positions + 1)
    e = np.exp(log_e)
    starts = []
    for alpha in (0.0, alpha_share * e.min()):
        y = np.log(e - alpha)
        log_alpha = np.log(alpha) if alpha > 0 else log_e.min() - 30
        for chosen in itertools.combinations(corners, b):
            design = np.column_stack([np.ones_like(x), x, *(np.maximum(x - c, 0) for c in chosen)])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            sse = float(np.sum((design @ coef - y) ** 2))
            breaks = [v for c, d in zip(chosen, coef[2:], strict=True) for v in (c, phi, d)]
            starts.append((sse, np.array([log_alpha, coef[0], coef[1], *breaks])))
    return sorted(starts, key=lambda start: start[0])


def refine_margin(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray, bounds: Bounds) -> np.ndarray:
    """Minimise the margin from ``theta`` (bounded trust-region least squares on the log residuals)."""
    result = least_squares(lambda t: log_law(t, x) - log_e, bounds.clip(theta),
                           jac=lambda t: log_law_jacobian(t, x), bounds=(bounds.lower, bounds.upper),
                           x_scale="jac", max_nfev=200)
    return result.x


def refine_study(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray, bounds: Bounds, steps: int, lr: float
                 ) -> np.ndarray:
    """The study's fit: Adam on mean_k(5 max(L - e~, 0) + max(e~ - L, 0)), projected onto the bounds."""
    e = np.exp(log_e)
    param = torch.nn.Parameter(torch.from_numpy(bounds.clip(theta).copy()))
    optimizer = torch.optim.Adam([param], lr=lr)
    for _ in range(steps):
        t = param.detach().numpy()
        law = np.exp(log_law(t, x))
        weight = np.where(law > e, 5.0, -1.0) / len(x)  # d loss / d L
        param.grad = torch.from_numpy((weight * law) @ log_law_jacobian(t, x))
        optimizer.step()
        with torch.no_grad():
            param.copy_(torch.from_numpy(bounds.clip(param.detach().numpy())))
    return param.detach().numpy()


def fit_breaks(x: np.ndarray, log_e: np.ndarray, b: int, settings: "FitSettings") -> np.ndarray:
    """The best theta with b breaks over the top ``settings.starts`` piecewise-linear starts."""
    bounds = Bounds.for_grid(x, log_e, b, settings.max_slope, settings.edge, settings.phi_min)
    starts = piecewise_linear_starts(x, log_e, b, settings.positions, settings.alpha_share,
                                     settings.phi_min)[:settings.starts]
    best, best_margin = None, math.inf
    for _, theta in starts:
        if settings.objective == "study":
            theta = refine_study(theta, x, log_e, bounds, settings.study_steps, settings.study_lr)
        else:
            theta = refine_margin(theta, x, log_e, bounds)
        m = margin_of(theta, x, log_e)
        if m < best_margin:
            best, best_margin = theta, m
    return best


@dataclass(frozen=True)
class FitSettings:
    """How the fit searches; the values and their meaning live in conf/nsl/default.yaml (``nsl_hpc.nsl``
    reads them)."""

    objective: str
    positions: int
    starts: int
    alpha_share: float
    max_slope: float
    edge: float
    phi_min: float
    min_gain: float
    margin_floor: float
    study_steps: int
    study_lr: float

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], **changes: Any) -> "FitSettings":
        """Settings from an ``nsl`` config (other keys ignored), with ``changes`` applied."""
        return cls(**{name: changes.get(name, values[name]) for name in cls.__dataclass_fields__})


def choose_breaks(margins: dict[int, float], min_gain: float, margin_floor: float) -> int:
    """b minimising ln max(M_b, floor) + b ln(1 / (1 - min_gain)), the smallest on ties: each break must
    cut the margin by at least ``min_gain`` (and not merely below the floor) to be worth it."""
    penalty = math.log(1 / (1 - min_gain))
    score = {b: math.log(max(m, margin_floor)) + b * penalty for b, m in margins.items()}
    return min(score, key=lambda b: (round(score[b], 12), b))


def validated_outcomes(resources: Sequence[float], errors: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    r, e = np.asarray(resources, dtype=float).ravel(), np.asarray(errors, dtype=float).ravel()
    if r.shape != e.shape:
        raise NSLFitError(f"{r.size} resources but {e.size} errors")
    if r.size == 0:
        raise NSLFitError("no outcomes to fit")
    for name, values in (("resource", r), ("error", e)):
        bad = ~np.isfinite(values) | (values <= 0)
        if bad.any():
            raise NSLFitError(f"{bad.sum()} of {values.size} {name} values are not finite and positive "
                              f"(first: {values[bad][0]!r}); drop them before fitting")
    if r.min() == r.max():
        raise NSLFitError(f"every outcome has the same resource value {r[0]:g}: no scaling to fit")
    return r, e


def uncentered(theta: np.ndarray, middle: float) -> np.ndarray:
    """theta for x from theta fitted for x - middle."""
    theta = theta.copy()
    theta[1] -= theta[2] * middle
    theta[3::3] += middle
    return theta


def fit_broken_law(resources: Sequence[float], errors: Sequence[float], breaks: int | None, max_breaks: int, K: int,
                   settings: FitSettings) -> NSLFit:
    """Fit a broken NSL to the lower envelope of the outcomes (resources[i], errors[i]).

    ``breaks``: a fixed number of breaks b; None chooses b in 0..``max_breaks`` (see choose_breaks).
    ``K``: envelope points. ``settings``: the search.
    Raises NSLFitError for outcomes that cannot be fitted."""
    if settings.objective not in OBJECTIVES:
        raise NSLFitError(f"objective={settings.objective!r}; choose from {', '.join(OBJECTIVES)}")
    if K < 2:
        raise NSLFitError(f"K={K}: the envelope needs at least 2 points")
    r, e = validated_outcomes(resources, errors)
    grid_r, grid_e = lower_envelope(r, e, K)
    x, log_e = np.log(grid_r), np.log(grid_e)
    middle = (x[0] + x[-1]) / 2  # fitted around the middle of the range: beta and delta0 decouple
    choices = [breaks] if breaks is not None else range(max_breaks + 1)
    thetas = {b: uncentered(fit_breaks(x - middle, log_e, b, settings), middle) for b in choices}
    margins = {b: margin_of(theta, x, log_e) for b, theta in thetas.items()}
    chosen = breaks if breaks is not None else choose_breaks(margins, settings.min_gain, settings.margin_floor)
    theta = thetas[chosen]
    alpha = float(np.exp(theta[0]))
    if margin_of(np.concatenate([[-np.inf], theta[1:]]), x, log_e) <= margins[chosen] * (1 + 1e-9):
        alpha = 0.0  # a negligible alpha is reported as none
    return NSLFit(alpha=alpha, beta=float(np.exp(theta[1])), delta0=float(theta[2]),
                  breaks=[(float(np.exp(s)), float(p), float(d)) for s, p, d in theta[3:].reshape(-1, 3)],
                  margin=margins[chosen], envelope_r=grid_r, envelope_e=grid_e, margins=margins,
                  objective=settings.objective)


@dataclass(frozen=True)
class Backtest:
    """A law fitted on the outcomes with resource <= ``cut`` and scored on the full envelope above it:
    ``margin`` = mean (ln L - ln E)^2 there, ``final_ratio`` = L / E at the largest resource."""

    cut: float
    fit: NSLFit
    margin: float
    final_ratio: float


def backtest_broken_law(resources: Sequence[float], errors: Sequence[float], cut: float, breaks: int | None,
                        max_breaks: int, K: int, settings: FitSettings) -> Backtest:
    """Extrapolation check: how well the law of the early outcomes forecasts the later envelope."""
    r, e = validated_outcomes(resources, errors)
    early = r <= cut
    if not early.any() or early.all():
        raise NSLFitError(f"cut={cut:g} leaves no outcomes on one side (resources {r.min():g} to {r.max():g})")
    fit = fit_broken_law(r[early], e[early], breaks, max_breaks, K, settings)
    grid_r, grid_e = lower_envelope(r, e, K)
    above = grid_r > cut
    log_ratio = np.log(fit.predict(grid_r[above])) - np.log(grid_e[above])
    return Backtest(cut, fit, float(np.mean(log_ratio**2)), float(np.exp(log_ratio[-1])))
