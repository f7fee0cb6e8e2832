"""Broken neural scaling laws (Definition 1 of the study), fitted without a hand-made initial guess.

For outcomes (r_i, e_i) (r: compute, data or parameters; e: nMAE or nMSE):

- lower envelope E(r) = min{e_i : r_i <= r}, sampled at K log-spaced resources r~_k from min r to max r
  (or its log-log interpolation between the outcomes on it, the study's named alternative);
- law L(r) = alpha + beta r^delta0 prod_i [1 + (r / sigma_i)^(1 / phi_i)]^(delta_i phi_i),
  alpha, beta >= 0, sigma_i > 0, phi_i >= phi_min (conf/nsl/default.yaml);
- margin M = mean_k (ln L(r~_k) - ln E(r~_k))^2 (natural logarithms).

Everything is evaluated in log space, ln L = logaddexp(ln alpha, ln beta + delta0 x
+ sum_i delta_i phi_i softplus((x - ln sigma_i) / phi_i)) with x = ln r, so resources up to 1e15 and errors
down to 1e-8 neither overflow nor underflow. The law is piecewise linear in log-log space with smooth
corners; its segments' slopes are s_0 = delta0 and s_k = delta0 + delta_1 + ... + delta_k (breaks in order of
sigma). An envelope never rises, so neither may a law of it: the search runs over the slopes themselves (the
slope form, see theta_of), boxed in [-max_slope, max_rise]. It starts from piecewise-linear least-squares fits
of the envelope with corners at every combination of candidate positions on the log grid and at the best
segmentation of the grid, plus a few random starts and the best law with one break fewer plus a flat break
(b = 0, 1, ... in turn), refines them with bounded least squares on the log residuals (MarginLoss: a residual
where the law lies above the envelope weighed above_weight, Section 4.3's beta, and optionally Huber's loss beyond
huber_delta; with neither it minimises M directly), and picks the number of breaks b by a penalised margin that
leaves out the envelope points the law fits worst, among the laws whose every segment stands on enough outcomes of
the envelope (choose_breaks).
"""

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares, lsq_linear
from scipy.special import expit

from nsl_hpc.config.schema import field_names, setting, typed
from nsl_hpc.core.errors import require_number
from nsl_hpc.core.law import NSLFit, log_law, log_power, slopes, softplus

OBJECTIVES = ("margin", "study")
ENVELOPES = ("step", "interpolated")
SUPPORT_MARGIN = 1e-9  # a boxed break stays this far (ln r) from the outcomes it must keep on either side: the law's
#                        segments count them again after uncentring (segment_points), whose rounding is ~1e-14
SLOPE_AT_BOUND = 0.01  # a slope this close to -max_slope was stopped by the bound


class NSLFitError(ValueError):
    """Outcomes that cannot be fitted (empty, a single resource value, non-positive or NaN values)."""


def pareto_indices(resources: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Indices of the outcomes on the lower envelope, by increasing resource: each has a smaller error than
    every outcome with a smaller resource (of outcomes with equal resources, the best)."""
    order = np.lexsort((errors, resources))
    running_min = np.minimum.accumulate(errors[order])
    return order[np.concatenate([[True], running_min[1:] < running_min[:-1]])]


def pareto_points(resources: np.ndarray, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(resources, errors) of the outcomes on the lower envelope (pareto_indices)."""
    on = pareto_indices(resources, errors)
    return resources[on], errors[on]


def lower_envelope(resources: np.ndarray, errors: np.ndarray, points: int, kind: str = "step"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(r~, e~): ``points`` log-spaced resources from the smallest to the largest and the envelope there.

    ``step``: Definition 1, the smallest error of the outcomes with a resource at most r~_k (a staircase).
    ``interpolated``: the study's alternative (Section 4): straight lines in log-log between consecutive
    outcomes on the envelope, so a sparse envelope has finite slopes instead of vertical steps."""
    if kind not in ENVELOPES:
        raise NSLFitError(f"envelope={kind!r}; choose from {', '.join(ENVELOPES)}")
    r, e = np.asarray(resources, dtype=float), np.asarray(errors, dtype=float)
    pareto_r, pareto_e = pareto_points(r, e)
    grid = np.geomspace(r.min(), r.max(), points)
    grid[0], grid[-1] = r.min(), r.max()
    if kind == "interpolated":
        return grid, np.exp(np.interp(np.log(grid), np.log(pareto_r), np.log(pareto_e)))
    return grid, pareto_e[np.searchsorted(pareto_r, grid, side="right") - 1]


def log_law_jacobian(theta: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d ln L / d theta, shape (len(x), len(theta))."""
    y = log_power(theta, x)
    w = expit(y - theta[0])  # share of the power term in L
    columns = [1 - w, w, w * x]
    for log_sigma, phi, delta in theta[3:].reshape(-1, 3):
        z = (x - log_sigma) / phi
        sigmoid, soft = expit(z), softplus(z)
        columns += [-w * delta * sigmoid, w * delta * (soft - z * sigmoid), w * phi * soft]
    return np.stack(columns, axis=1)


def slope_form(theta: np.ndarray) -> np.ndarray:
    """u = [ln alpha, ln beta, s_0, (ln sigma_k, phi_k, s_k) ...] of theta, its breaks in order of sigma."""
    breaks = theta[3:].reshape(-1, 3)
    u = np.concatenate([theta[:3], breaks[np.argsort(breaks[:, 0], kind="stable")].ravel()])
    u[2::3] = slopes(theta)
    return u


def theta_of(u: np.ndarray) -> np.ndarray:
    """theta of the slope form u: the k-th break (corner phi_k, slope s_k beyond it) sits at the k-th smallest
    position of u, delta_k = s_k - s_{k-1}. Positions that cross swap nothing else, so the law is continuous
    in u and, boxed in [-max_slope, max_rise] on the slopes, can never rise faster than max_rise."""
    theta = u.copy()
    theta[3::3] = np.sort(u[3::3])
    theta[5::3] = np.diff(u[2::3])
    return theta


def slope_form_jacobian(u: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d ln L / d u, shape (len(x), len(u))."""
    jacobian = log_law_jacobian(theta_of(u), x)
    by_slope = jacobian.copy()
    delta = jacobian[:, 2::3]  # d / d delta0, d / d delta_1, ...
    by_slope[:, 2:-3:3] = delta[:, :-1] - delta[:, 1:]  # s_k moves delta_k and, the other way, delta_k+1
    rank = np.argsort(np.argsort(u[3::3], kind="stable"), kind="stable")
    by_slope[:, 3::3] = jacobian[:, 3::3][:, rank]
    return by_slope


def margin_of(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray) -> float:
    return float(np.mean((log_law(theta, x) - log_e) ** 2))


def weighted_residuals(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray, above_weight: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(the log residuals ln L - ln e~ of the law theta on the envelope, each scaled by sqrt(above_weight) where
    the law lies above the envelope, the scales): what the margin objective squares and averages."""
    residuals = log_law(theta, x) - log_e
    scales = np.where(residuals > 0, np.sqrt(above_weight), 1.0)
    return scales * residuals, scales


@dataclass(frozen=True)
class MarginLoss:
    """The margin objective's loss of the log residuals: one where the law lies above the envelope weighs
    ``above_weight``, and ``huber_delta`` (None: none) bounds the pull of a point off the law (Huber's loss:
    quadratic up to that weighted log residual, linear beyond; scipy's least_squares ``loss="huber"``)."""

    above_weight: float
    huber_delta: float | None

    def of(self, weighted: np.ndarray) -> np.ndarray:
        """(K,) each point's loss from its weighted log residual."""
        squared = weighted**2
        if self.huber_delta is None:
            return squared
        scaled = squared / self.huber_delta**2
        return self.huber_delta**2 * np.where(scaled <= 1, scaled, 2 * np.sqrt(scaled) - 1)

    def least_squares_loss(self) -> dict[str, Any]:
        """least_squares' arguments for this loss."""
        return {"loss": "linear"} if self.huber_delta is None else {"loss": "huber", "f_scale": self.huber_delta}


def margin_objective(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray, loss: MarginLoss) -> float:
    """The margin objective: the mean ``loss`` of the log residuals on the envelope (the plain loss: M,
    Definition 1's margin)."""
    return float(np.mean(loss.of(weighted_residuals(theta, x, log_e, loss.above_weight)[0])))


@dataclass(frozen=True)
class Bounds:
    """Box bounds of the slope form u (slope_form) for b breaks on the log grid ``x`` with log errors
    ``log_e``."""

    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def for_grid(cls, x: np.ndarray, log_e: np.ndarray, b: int, settings: "FitSettings") -> "Bounds":
        """Slopes in [-max_slope, max_rise]; breaks stay ``edge`` of the log range inside it: a corner at the
        very end of the data is not identifiable (it fits the scatter of the few outcomes that make the
        envelope there)."""
        max_slope, phi_min = settings.max_slope, settings.phi_min
        span = max(x[-1] - x[0], phi_min)
        lower = [log_e.min() - 30, log_e.min() - 30 - max_slope * np.abs(x).max(), -max_slope]
        upper = [log_e.max(), log_e.max() + 30 + max_slope * np.abs(x).max(), settings.max_rise]
        lower += [x[0] + settings.edge * span, phi_min, -max_slope] * b
        upper += [x[-1] - settings.edge * span, max(span, phi_min * 1.01), settings.max_rise] * b
        return cls(np.array(lower, dtype=float), np.array(upper, dtype=float))

    def clip(self, theta: np.ndarray) -> np.ndarray:
        return np.clip(theta, self.lower, self.upper)

    def keeping_support(self, u: np.ndarray, x_on: np.ndarray, points: int) -> "Bounds":
        """These bounds narrowed around the slope form ``u`` (positions in order) so that every segment keeps
        ``points`` of the outcomes on the envelope (log resources ``x_on``, increasing): a break may take at most
        half the spare outcomes of an inner segment beside it, and all of those of the first or last."""
        counts = segment_points(u, x_on)
        firsts = np.cumsum(counts)[:-1]  # index in x_on of the first outcome right of each break
        spare = counts - points
        lower, upper = self.lower.copy(), self.upper.copy()
        for k, first in enumerate(firsts):
            take_left = spare[k] if k == 0 else spare[k] // 2
            take_right = spare[k + 1] if k == len(firsts) - 1 else spare[k + 1] // 2
            lower[3 + 3 * k] = max(lower[3 + 3 * k], x_on[first - take_left - 1] + SUPPORT_MARGIN)
            upper[3 + 3 * k] = min(upper[3 + 3 * k], x_on[first + take_right] - SUPPORT_MARGIN)
        return Bounds(lower, np.maximum(upper, np.nextafter(lower, np.inf)))


def segment_costs(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(K+1, K+1): [i, j] = squared error of the least-squares line through points i..j-1 (inf for < 2)."""
    sums = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(x), x, y, x * x, x * y, y * y)]
    n, sx, sy, sxx, sxy, syy = (s[None, :] - s[:, None] for s in sums)
    with np.errstate(divide="ignore", invalid="ignore"):
        var_x, cov, var_y = sxx - sx * sx / n, sxy - sx * sy / n, syy - sy * sy / n
        sse = var_y - np.where(var_x > 1e-12, cov * cov / np.where(var_x > 1e-12, var_x, 1.0), 0.0)
    return np.where(n >= 2, np.maximum(sse, 0.0), np.inf)


def best_segmentation(x: np.ndarray, y: np.ndarray, b: int) -> list[int]:
    """Inner boundaries of the b + 1 contiguous runs of grid points whose separate line fits leave the least
    squared error (dynamic programming over every boundary position, O(b K^2))."""
    costs = segment_costs(x, y)
    best, choices = costs[0], list[np.ndarray]()
    for _ in range(b):
        total = best[:, None] + costs
        choice = np.argmin(total, axis=0)
        best, choices = total[choice, np.arange(len(best))], [*choices, choice]
    boundaries = [len(x)]
    for choice in reversed(choices):
        boundaries.append(int(choice[boundaries[-1]]))
    return sorted(boundaries[1:])


def hinge_fit(x: np.ndarray, y: np.ndarray, corners: Sequence[float], slope_range: tuple[float, float]
              ) -> np.ndarray:
    """Least-squares continuous piecewise-linear fit of y(x) with these corners (increasing), every segment's
    slope in ``slope_range``: [intercept, first slope, slope change at each corner]."""
    hinges = [np.maximum(x - c, 0) for c in corners]
    design = np.column_stack([np.ones_like(x), x, *hinges])
    coef = np.linalg.lstsq(design, y, rcond=None)[0]
    segment_slopes = np.cumsum(coef[1:])
    if slope_range[0] <= segment_slopes.min() and segment_slopes.max() <= slope_range[1]:
        return coef
    # in the segments' slopes s_k: y = a + s_0 x + sum_k (s_k - s_{k-1}) max(x - c_k, 0), the range a box
    by_slope = np.column_stack([np.ones_like(x), x - (hinges[0] if hinges else 0),
                                *(hinge - (hinges[k + 1] if k + 1 < len(hinges) else 0)
                                  for k, hinge in enumerate(hinges))])
    lower, upper = [-np.inf] + [slope_range[0]] * (len(corners) + 1), [np.inf] + [slope_range[1]] * (len(corners) + 1)
    solution = lsq_linear(by_slope, y, bounds=(lower, upper), method="bvls").x
    return np.concatenate([solution[:2], np.diff(solution[1:])])


def piecewise_linear_starts(x: np.ndarray, log_e: np.ndarray, b: int, settings: "FitSettings") -> list[np.ndarray]:
    """Initial thetas from continuous piecewise-linear least-squares fits of ln(e~ - alpha) with slopes in
    [-max_slope, max_rise], alpha = 0 and alpha = each of ``alpha_shares`` * min e~, with corners (a) at every
    combination of b of ``positions`` evenly spaced inner points of the log grid and (b) at the boundaries of the
    best segmentation of the grid (which finds breaks closer together than the even positions are)."""
    positions, alpha_shares, phi_min = settings.positions, settings.alpha_shares, settings.phi_min
    span = x[-1] - x[0]
    phi = max(phi_min, 0.03 * span)
    even = x[0] + span * np.arange(1, positions + 1) / (positions + 1)
    e = np.exp(log_e)
    starts = []
    for alpha in (0.0, *(share * e.min() for share in alpha_shares)):
        y = np.log(e - alpha)
        log_alpha = np.log(alpha) if alpha > 0 else log_e.min() - 30
        segmented = [tuple((x[i - 1] + x[i]) / 2 for i in best_segmentation(x, y, b))] if b else []
        for corners in [*itertools.combinations(even, b), *segmented]:
            coef = hinge_fit(x, y, corners, (-settings.max_slope, settings.max_rise))
            breaks = [v for c, d in zip(corners, coef[2:], strict=True) for v in (c, phi, d)]
            starts.append(np.array([log_alpha, coef[0], coef[1], *breaks]))
    return starts


def random_starts(x: np.ndarray, log_e: np.ndarray, b: int, count: int, bounds: Bounds, seed: int
                  ) -> list[np.ndarray]:
    """``count`` random slope forms in ``bounds`` (positions uniform in range, slope changes and phi moderate,
    alpha 0 or a share of min e~ drawn from U(0.5, 1)), each through the first envelope point: starts that no
    structured guess supplies (e.g. a saturating alpha together with a break)."""
    rng = np.random.default_rng(seed)
    starts = []
    for _ in range(count):
        log_alpha = log_e.min() + np.log(rng.uniform(0.5, 1.0)) if rng.random() < 0.5 else bounds.lower[0]
        breaks = [v for position in np.sort(rng.uniform(bounds.lower[3], bounds.upper[3], b))
                  for v in (position, rng.uniform(bounds.lower[4], 1.0), rng.uniform(-3, 3))] if b else []
        theta = np.array([log_alpha, 0.0, rng.uniform(-2, 1), *breaks])
        theta[1] = log_e[0] - log_power(theta, x[:1])[0]  # through (x_0, e~_0)
        starts.append(bounds.clip(slope_form(theta)))
    return starts


def refine_margin(u: np.ndarray, x: np.ndarray, log_e: np.ndarray, bounds: Bounds, evaluations: int,
                  loss: MarginLoss) -> np.ndarray:
    """Minimise the margin objective (``margin_objective``) from the slope form ``u`` (bounded trust-region least
    squares on the weighted log residuals with ``loss``, at most ``evaluations`` evaluations; stops when it changes
    by less than 1e-6 of itself)."""
    above_weight = loss.above_weight
    evaluated: dict[bytes, np.ndarray] = {}  # the scales at the last point the residuals were evaluated at

    def residuals(v: np.ndarray) -> np.ndarray:
        weighted, scales = weighted_residuals(theta_of(v), x, log_e, above_weight)
        evaluated.clear()
        evaluated[v.tobytes()] = scales
        return weighted

    def jacobian(v: np.ndarray) -> np.ndarray:  # least squares asks for it where it last evaluated the residuals
        scales = evaluated.get(v.tobytes())
        if scales is None:
            scales = weighted_residuals(theta_of(v), x, log_e, above_weight)[1]
        return scales[:, None] * slope_form_jacobian(v, x)

    result = least_squares(residuals, bounds.clip(u), jac=jacobian, bounds=(bounds.lower, bounds.upper),
                           x_scale="jac", max_nfev=evaluations, ftol=1e-6, **loss.least_squares_loss())
    return result.x


def study_loss(u: np.ndarray, x: np.ndarray, e: np.ndarray, beta: float) -> tuple[float, np.ndarray]:
    """Section 4.3's loss mean_k(beta max(L - e~, 0) + max(e~ - L, 0)) at the slope form u, and its gradient."""
    law = np.exp(log_law(theta_of(u), x))
    above = law > e
    loss = float(np.mean(np.where(above, beta * (law - e), e - law)))
    weight = np.where(above, beta, -1.0) / len(x)  # d loss / d L
    return loss, (weight * law) @ slope_form_jacobian(u, x)


def refine_study(u: np.ndarray, x: np.ndarray, log_e: np.ndarray, settings: "FitSettings") -> np.ndarray:
    """Section 4.3 as written: Adam on the study's loss over the slope form [ln alpha, ln beta, s_0,
    (ln sigma_i, phi_i, s_i)...], unbounded but for phi_i, held at ``study_phi`` (the published laws' 0.2) or,
    with study_phi = null, kept >= phi_min (the study's max(phi_i, 0.2)), and the slopes, kept <= max_rise.
    Returns the iterate of least loss (the loss is piecewise linear: a constant-rate Adam circles its minimum
    instead of settling)."""
    import torch  # here, not with the module: fits by the default objective (margin) start without it

    u = u.copy()
    phis, rises = np.zeros(len(u), dtype=bool), np.zeros(len(u), dtype=bool)
    phis[4::3], rises[2::3] = True, True
    u[phis] = settings.study_phi if settings.study_phi is not None else np.maximum(u[phis], settings.phi_min)
    u[rises] = np.minimum(u[rises], settings.max_rise)
    e = np.exp(log_e)
    param = torch.nn.Parameter(torch.from_numpy(u))
    optimizer = torch.optim.Adam([param], lr=settings.study_lr)
    best, best_loss = u.copy(), math.inf
    for _ in range(settings.study_steps):
        loss, gradient = study_loss(param.detach().numpy(), x, e, settings.study_beta)
        if loss < best_loss:
            best, best_loss = param.detach().numpy().copy(), loss
        if settings.study_phi is not None:
            gradient[phis] = 0.0
        param.grad = torch.from_numpy(gradient)
        optimizer.step()
        with torch.no_grad():
            param[torch.from_numpy(phis)] = param[torch.from_numpy(phis)].clamp(min=settings.phi_min)
            param[torch.from_numpy(rises)] = param[torch.from_numpy(rises)].clamp(max=settings.max_rise)
    return best


def refine(u: np.ndarray, x: np.ndarray, log_e: np.ndarray, b: int, settings: "FitSettings",
           evaluations: int = 200) -> np.ndarray:
    """The slope form ``u`` refined by the settings' objective (``evaluations``: the margin objective's
    budget)."""
    if settings.objective == "study":
        return refine_study(u, x, log_e, settings)
    return refine_margin(u, x, log_e, Bounds.for_grid(x, log_e, b, settings), evaluations, settings.margin_loss)


def with_flat_break(theta: np.ndarray, x: np.ndarray, positions: int, phi_min: float) -> list[np.ndarray]:
    """theta with one more break of zero slope change at each of ``positions`` even inner points of the log
    grid: the same law, so a search from them can only improve on the law with one break fewer."""
    phi = max(phi_min, 0.03 * (x[-1] - x[0]))
    even = x[0] + (x[-1] - x[0]) * np.arange(1, positions + 1) / (positions + 1)
    return [np.concatenate([theta, [position, phi, 0.0]]) for position in even]


def fit_breaks(x: np.ndarray, log_e: np.ndarray, b: int, settings: "FitSettings", x_on: np.ndarray | None,
               fewer: Sequence[np.ndarray] = ()) -> tuple[np.ndarray, np.ndarray | None]:
    """The best theta with b breaks, and (given ``x_on``, the log resources of the outcomes on the envelope) the
    best whose every segment stands on ``settings.min_segment_points`` of them (None when none is found), from the
    top ``settings.starts`` piecewise-linear starts, ``settings.random_starts`` random ones (seeded: a fit depends
    only on its outcomes and settings) and each law of ``fewer`` (laws with b - 1 breaks) with a flat break added,
    by the settings' objective: each refined briefly (the study's Adam: ranked as they start), the best
    ``settings.finalists`` to the end; where none of those stands on enough outcomes, the best as many that do
    are refined to the end with each break boxed where its segments keep them. Every start is put in the bounds
    of the slope form first (its slopes within them)."""
    bounds = Bounds.for_grid(x, log_e, b, settings)

    def objective(u: np.ndarray) -> float:
        if settings.objective == "study":
            return study_loss(u, x, np.exp(log_e), settings.study_beta)[0]
        return margin_objective(theta_of(u), x, log_e, settings.margin_loss)

    def supported(u: np.ndarray) -> bool:
        return x_on is not None and bool(segment_points(u, x_on).min() >= settings.min_segment_points)

    starts = [bounds.clip(slope_form(theta)) for theta in
              piecewise_linear_starts(x, log_e, b, settings)]
    chosen = sorted(starts, key=lambda u: margin_objective(theta_of(u), x, log_e, settings.margin_loss)
                    )[:settings.starts]
    chosen += random_starts(x, log_e, b, settings.random_starts, bounds, seed=b)
    for law in fewer:
        chosen += [bounds.clip(slope_form(theta)) for theta in with_flat_break(law, x, 3, settings.phi_min)]
    if settings.objective == "margin":  # a short refinement of every start ...
        chosen = [refine(u, x, log_e, b, settings, evaluations=30) for u in chosen]
    ranked = sorted(chosen, key=objective)
    refined = sorted((refine(u, x, log_e, b, settings) for u in ranked[:settings.finalists]), key=objective)
    standing = [u for u in refined if supported(u)]  # ... the best to the end
    if x_on is not None and not standing:  # the best standing ones, kept standing while refined
        for u in [u for u in ranked if supported(u)][:settings.finalists]:
            u = slope_form(theta_of(u))
            standing.append(refine_margin(u, x, log_e, bounds.keeping_support(u, x_on, settings.min_segment_points),
                                          200, settings.margin_loss) if settings.objective == "margin" else u)
        standing.sort(key=objective)
    return theta_of(refined[0]), theta_of(standing[0]) if standing else None


@dataclass(frozen=True)
class FitSettings:
    """How the fit searches: the typed owner of these keys of the ``nsl`` group (conf/nsl/default.yaml holds the
    values; ``nsl_hpc.nsl.default_settings`` reads them)."""

    objective: str = setting("margin: least squares on the log residuals; study: Section 4.3 as written",
                             choices=OBJECTIVES)
    above_weight: float = setting("objective=margin: the weight of a squared log residual where the law lies above "
                                  "the envelope (Section 4.3's beta; 1: plain least squares, minimising M)", 1)
    huber_delta: float | None = setting("objective=margin: Huber's threshold of the weighted log residuals (a point "
                                        "further off pulls linearly); null: plain squares", 0, low_open=True)
    envelope: str = setting("what objective=margin fits: Definition 1's step envelope or the interpolated one",
                            choices=ENVELOPES)
    positions: int = setting("candidate corner positions of the piecewise-linear starts", 1)
    starts: int = setting("piecewise-linear starts refined per b", 1)
    random_starts: int = setting("random starts refined briefly per b", 0)
    finalists: int = setting("the best this many refined to the end", 1)
    alpha_shares: list[float] = setting("alpha starts besides 0, as shares of the smallest envelope error", 0, 1,
                                        high_open=True)
    max_slope: float = setting("every segment's log-log slope is >= -max_slope", 0, low_open=True)
    max_rise: float = setting("... and <= max_rise", 0)
    min_segment_points: int = setting("choice of b: every segment stands on this many outcomes of the envelope", 1)
    edge: float = setting("breaks stay this share of the log resource range inside it", 0, 0.5, high_open=True)
    phi_min: float = setting("smallest corner sharpness phi_i", 0, low_open=True)
    min_gain: float = setting("choice of b: each break must cut the trimmed margin by this share", 0, 1,
                              high_open=True)
    choice_trim: float = setting("choice of b: the margin without this share of the worst-fitted envelope points",
                                 0, 1, high_open=True)
    margin_floor: float = setting("margins below this floor count as the floor", 0)
    study_beta: float = setting("objective=study: the weight of L above the envelope (Section 4.3)", 0)
    study_phi: float | None = setting("objective=study: every phi_i held here; null frees it (>= phi_min)", 0)
    study_steps: int = setting("objective=study: Adam steps per start", 1)
    study_lr: float = setting("objective=study: Adam's learning rate", 0, low_open=True)

    @classmethod
    def of(cls, values: Mapping[str, Any], **changes: Any) -> "FitSettings":
        """The search settings of an ``nsl`` group (its other keys left out), ``changes`` applied, checked."""
        search = {name: changes.get(name, values[name]) for name in field_names(FitSettings)}
        return typed(FitSettings, search, "nsl")

    @property
    def margin_loss(self) -> MarginLoss:
        """The margin objective's loss."""
        return MarginLoss(self.above_weight, self.huber_delta)

    @property
    def fitted_envelope(self) -> str:
        """The envelope the fit minimises its objective on: the study's procedure fits Definition 1's."""
        return "step" if self.objective == "study" else self.envelope

    def check(self) -> None:
        """The rules between the fields (a ConfigError naming the ``nsl`` key)."""
        require_number("nsl.max_rise", self.max_rise, 0, self.max_slope)
        if self.study_phi is not None:
            require_number("nsl.study_phi", self.study_phi, self.phi_min)


def trimmed_margin(theta: np.ndarray, x: np.ndarray, log_e: np.ndarray, trim: float) -> float:
    """The margin without the ``trim`` share of envelope points that the law fits worst (at least one when
    trim > 0): what is left once a lone outcome that makes the envelope's first point or one of its steps no
    longer counts."""
    squared = np.sort((log_law(theta, x) - log_e) ** 2)
    drop = math.ceil(trim * len(squared)) if trim > 0 else 0
    return float(np.mean(squared[:len(squared) - drop]))


def segment_points(theta: np.ndarray, x_on: np.ndarray) -> np.ndarray:
    """(b + 1,): how many of the outcomes on the envelope (log resources ``x_on``, pareto_points) each segment of
    the law (theta or its slope form) stands on: below its first break, between consecutive breaks, beyond its
    last."""
    edges = np.sort(theta[3::3])
    return np.bincount(np.searchsorted(edges, x_on), minlength=len(edges) + 1)


def undetermined_segments(theta: np.ndarray, points: np.ndarray, settings: "FitSettings") -> dict[int, str]:
    """Segment k -> why its slope is not determined by the outcomes: at the slope bound -max_slope (a cliff the
    bound cut, not a measured slope), or standing on fewer than min_segment_points outcomes of the envelope."""
    reasons: dict[int, list[str]] = {}
    for k, (slope, count) in enumerate(zip(slopes(theta), points, strict=True)):
        if slope <= -settings.max_slope + SLOPE_AT_BOUND:
            reasons.setdefault(k, []).append(f"at the slope bound -{settings.max_slope:g}")
        if count < settings.min_segment_points:
            reasons.setdefault(k, []).append(f"on {count} envelope outcome{'' if count == 1 else 's'}")
    return {k: " and ".join(why) for k, why in reasons.items()}


def choose_breaks(margins: dict[int, float], min_gain: float, margin_floor: float) -> int:
    """b minimising ln max(M_b, floor) + b ln(1 / (1 - min_gain)), the smallest on ties: each break must
    cut the margin by at least ``min_gain`` (and not merely below the floor) to be worth it. ``margins``:
    the trimmed margins (trimmed_margin) of the best law for each b."""
    penalty = math.log(1 / (1 - min_gain))
    score = {b: math.log(max(m, margin_floor)) + b * penalty for b, m in margins.items()}
    return min(score, key=lambda b: (round(score[b], 12), b))


def validated_outcomes(resources: ArrayLike, errors: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
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


def centred(theta: np.ndarray, middle: float) -> np.ndarray:
    """theta for x - middle from theta for x (fitting around the middle of the range decouples beta and
    delta0)."""
    theta = theta.copy()
    theta[1] += theta[2] * middle
    theta[3::3] -= middle
    return theta


def uncentred(theta: np.ndarray, middle: float) -> np.ndarray:
    """theta for x from theta for x - middle."""
    theta = theta.copy()
    theta[1] -= theta[2] * middle
    theta[3::3] += middle
    return theta


def law_of(theta: np.ndarray, r: np.ndarray, e: np.ndarray, grid_r: np.ndarray, grid_e: np.ndarray,
           settings: FitSettings, margins: dict[int, float]) -> NSLFit:
    """The NSLFit of theta fitted to the envelope (grid_r, grid_e) of outcomes (r, e): its margin is Definition
    1's (step envelope)."""
    step_e = grid_e if settings.fitted_envelope == "step" else lower_envelope(r, e, len(grid_r), "step")[1]
    x = np.log(grid_r)
    alpha = float(np.exp(theta[0]))
    loss = settings.margin_loss
    if margin_objective(np.concatenate([[-np.inf], theta[1:]]), x, np.log(grid_e), loss) <= \
            margin_objective(theta, x, np.log(grid_e), loss) * (1 + 1e-9):
        alpha = 0.0  # a negligible alpha is reported as none
    points = segment_points(theta, np.log(pareto_points(r, e)[0]))
    return NSLFit(alpha=alpha, beta=float(np.exp(theta[1])), delta0=float(theta[2]),
                  breaks=sorted((float(np.exp(s)), float(p), float(d)) for s, p, d in theta[3:].reshape(-1, 3)),
                  margin=margin_of(theta, x, np.log(step_e)), envelope_r=grid_r, envelope_e=grid_e,
                  margins=margins, objective=settings.objective, envelope=settings.fitted_envelope,
                  fit_margin=margin_of(theta, x, np.log(grid_e)), segment_points=tuple(int(n) for n in points),
                  undetermined=undetermined_segments(theta, points, settings))


def fit_broken_law(resources: ArrayLike, errors: ArrayLike, breaks: int | None, max_breaks: int, K: int,
                   settings: FitSettings) -> NSLFit:
    """Fit a broken NSL to the lower envelope of the outcomes (resources[i], errors[i]).

    ``breaks``: a fixed number of breaks b (the best law with b breaks); None chooses b in 0..``max_breaks`` (see
    choose_breaks) among the best laws whose every segment stands on at least ``settings.min_segment_points``
    outcomes of the envelope (b = 0 always counts).
    ``K``: envelope points. ``settings``: the search.
    Raises NSLFitError for outcomes that cannot be fitted."""
    if K < 2:
        raise NSLFitError(f"K={K}: the envelope needs at least 2 points")
    r, e = validated_outcomes(resources, errors)
    grid_r, grid_e = lower_envelope(r, e, K, settings.fitted_envelope)
    x, log_e = np.log(grid_r), np.log(grid_e)
    middle = (x[0] + x[-1]) / 2
    x_on = None if breaks is not None else np.log(pareto_points(r, e)[0]) - middle
    best: dict[int, np.ndarray] = {}  # b -> the best centred law ...
    standing: dict[int, np.ndarray] = {}  # ... and the best standing on enough outcomes of the envelope
    for b in range((breaks if breaks is not None else max_breaks) + 1):
        fewer = list({id(law): law for law in (best.get(b - 1), standing.get(b - 1)) if law is not None}.values())
        best[b], found = fit_breaks(x - middle, log_e, b, settings, x_on, fewer)
        if found is not None or b == 0:
            standing[b] = best[b] if found is None else found
    if breaks is not None:
        theta = uncentred(best[breaks], middle)
        return law_of(theta, r, e, grid_r, grid_e, settings, {breaks: margin_of(theta, x, log_e)})
    thetas = {b: uncentred(theta, middle) for b, theta in standing.items()}
    trimmed = {b: trimmed_margin(theta, x, log_e, settings.choice_trim) for b, theta in thetas.items()}
    chosen = choose_breaks(trimmed, settings.min_gain, settings.margin_floor)
    margins = {b: margin_of(theta, x, log_e) for b, theta in thetas.items()}
    return law_of(thetas[chosen], r, e, grid_r, grid_e, settings, margins)


def refit(fit: NSLFit, resources: np.ndarray, errors: np.ndarray, K: int, settings: FitSettings) -> np.ndarray:
    """theta of ``fit``'s law (same b) refined on other outcomes, e.g. a bootstrap resample."""
    grid_r, grid_e = lower_envelope(resources, errors, K, settings.fitted_envelope)
    x, log_e = np.log(grid_r), np.log(grid_e)
    middle = (x[0] + x[-1]) / 2
    with np.errstate(divide="ignore"):
        start = fit.parameters()
    start[0] = max(start[0], log_e.min() - 30)
    u = Bounds.for_grid(x - middle, log_e, fit.b, settings).clip(slope_form(centred(start, middle)))
    return uncentred(theta_of(refine(u, x - middle, log_e, fit.b, settings, evaluations=50)), middle)


@dataclass(frozen=True)
class Backtest:
    """A law fitted on the outcomes with resource <= ``cut`` and scored on the full envelope above it:
    ``margin`` = mean (ln L - ln E)^2 there, ``final_ratio`` = L / E at the largest resource."""

    cut: float
    fit: NSLFit
    margin: float
    final_ratio: float


def backtest_broken_law(resources: ArrayLike, errors: ArrayLike, cut: float, breaks: int | None,
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
