"""The public fitting API: fit a broken NSL to outcomes, or backtest its extrapolation.

    from nsl_hpc.nsl import fit_nsl
    fit = fit_nsl(resources, errors)            # b chosen in 0..4, the search of conf/nsl/default.yaml
    fit.alpha, fit.beta, fit.delta0, fit.breaks, fit.margin, fit.predict(r)

The maths lives in ``nsl_hpc.analysis.broken_law``; this module adds the default search settings.
"""

from typing import Any

from numpy.typing import ArrayLike
from omegaconf import OmegaConf

from nsl_hpc.analysis.broken_law import (
    Backtest,
    FitSettings,
    NSLFit,
    NSLFitError,
    backtest_broken_law,
    fit_broken_law,
    lower_envelope,
)
from nsl_hpc.config import config_dir, plain

__all__ = ["Backtest", "FitSettings", "NSLFit", "NSLFitError", "backtest_nsl", "default_settings", "fit_nsl",
           "lower_envelope"]


def default_settings(**changes: Any) -> FitSettings:
    """conf/nsl/default.yaml's search settings, with ``changes`` applied."""
    return FitSettings.of(plain(OmegaConf.load(config_dir() / "nsl" / "default.yaml")), **changes)


def fit_nsl(resources: ArrayLike, errors: ArrayLike, breaks: int | None = None, max_breaks: int = 4,
            K: int = 100, settings: FitSettings | None = None) -> NSLFit:
    """Fit a broken NSL to the lower envelope of the outcomes (resources[i], errors[i]).

    ``breaks``: a fixed number of breaks b; None chooses b in 0..``max_breaks``. ``K``: envelope points.
    ``settings``: the search (default: conf/nsl/default.yaml). Raises NSLFitError for outcomes that cannot
    be fitted."""
    return fit_broken_law(resources, errors, breaks, max_breaks, K, settings or default_settings())


def backtest_nsl(resources: ArrayLike, errors: ArrayLike, cut: float, breaks: int | None = None,
                 max_breaks: int = 4, K: int = 100, settings: FitSettings | None = None) -> Backtest:
    """Extrapolation check: the law fitted on the outcomes with resource <= ``cut``, scored above it."""
    return backtest_broken_law(resources, errors, cut, breaks, max_breaks, K, settings or default_settings())
