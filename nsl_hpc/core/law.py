"""The broken neural scaling law of Definition 1, as a value: its parameters, formula, segments' slopes and
predictions. Fitting it to outcomes is ``broken_law``'s; this module needs numpy alone (a rehearsal's jobs draw
their outcomes from planted laws without loading the fit's optimisers).

    L(r) = alpha + beta r^delta0 prod_i [1 + (r / sigma_i)^(1 / phi_i)]^(delta_i phi_i)

evaluated in log space: ln L = logaddexp(ln alpha, ln beta + delta0 x + sum_i delta_i phi_i softplus((x -
ln sigma_i) / phi_i)), x = ln r.
"""

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class NSLFit:
    """A fitted law; ``breaks`` holds (sigma, phi, delta) per break, by sigma. ``margin``: M of Definition 1 (on
    the step envelope, as the study reports it); ``envelope_r`` / ``envelope_e``: the K points of the ``envelope``
    the law was fitted to, ``fit_margin`` its margin there and ``margins`` the best such margin for each
    number of breaks tried. ``segment_points``: the outcomes on the envelope under each of the b + 1 segments;
    ``undetermined``: segment -> why the outcomes do not determine its slope (undetermined_segments)."""

    alpha: float
    beta: float
    delta0: float
    breaks: list[tuple[float, float, float]]
    margin: float
    envelope_r: np.ndarray = field(repr=False)
    envelope_e: np.ndarray = field(repr=False)
    margins: dict[int, float] = field(default_factory=dict)
    objective: str = "margin"
    envelope: str = "step"
    fit_margin: float | None = None
    segment_points: tuple[int, ...] = ()
    undetermined: dict[int, str] = field(default_factory=dict)

    @property
    def b(self) -> int:
        return len(self.breaks)

    @property
    def slopes(self) -> np.ndarray:
        """(b + 1,): the log-log slope of each segment (see slopes())."""
        return slopes(self.parameters())

    def predict(self, r: np.ndarray | float) -> np.ndarray:
        """L(r) for resources ``r`` (any shape)."""
        return np.exp(log_law(self.parameters(), np.log(np.asarray(r, dtype=float))))

    def segment_name(self, k: int) -> str:
        """Where segment k lies: 'below 3.1e+07', '3.1e+07 to 4.9e+07', 'beyond 4.9e+07' (b = 0: 'all')."""
        edges = [sigma for sigma, _, _ in self.breaks]
        if not edges:
            return "all"
        if k == 0:
            return f"below {edges[0]:.2g}"
        return f"beyond {edges[-1]:.2g}" if k == len(edges) else f"{edges[k - 1]:.2g} to {edges[k]:.2g}"

    def undetermined_text(self) -> str | None:
        """The undetermined segments in words, e.g. 'slope -10 beyond 4.9e+07: at the slope bound -10 and on 1
        envelope outcome'; None when the outcomes determine every slope."""
        if not self.undetermined:
            return None
        return "; ".join(f"slope {self.slopes[k]:.2f} {self.segment_name(k)}: {why}"
                         for k, why in sorted(self.undetermined.items()))

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


def slopes(theta: np.ndarray) -> np.ndarray:
    """(b + 1,): the log-log slopes s_0 = delta0, s_k = delta0 + delta_1 + ... + delta_k of the law's segments
    (breaks in order of sigma); s_b is the slope beyond the last break."""
    breaks = theta[3:].reshape(-1, 3)
    ordered = breaks[np.argsort(breaks[:, 0], kind="stable"), 2]
    return theta[2] + np.concatenate([[0.0], np.cumsum(ordered)])
