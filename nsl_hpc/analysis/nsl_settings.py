"""The typed owners of the post-processing settings: the ``nsl`` group (conf/nsl/default.yaml: the fits, their
intervals, predict's joint law), the ``figures`` group (conf/figures/default.yaml) and report's ``mlflow``.
``nsl_settings`` and ``figure_settings`` check a config's before any work, so that a bad value is one line and
nothing written is replaced (``config.schema``)."""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from nsl_hpc.analysis.broken_law import FitSettings
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.core.errors import ConfigError, require_choice, require_number

INTERVALS = ("basic", "percentile")
DRAWS = ("half", "replacement")


@dataclass(frozen=True)
class Resource:
    """A resource an NSL is fitted over."""

    column: str = setting("the results column")
    symbol: str = setting("its symbol in formulas")
    label: str = setting("its axis label")


@dataclass(frozen=True)
class ReportTargets:
    """The report's what-it-takes table: targets = factor x the best error."""

    resource: str = setting("the resource the table is for")
    metric: str = setting("the metric the table is for")
    factors: list[float] = setting("targets as multiples of the best error", 0, low_open=True, nonempty=True)


@dataclass(frozen=True)
class Predict:
    """What it takes (python -m nsl_hpc.predict, the report's section)."""

    decades: float = setting("the law is searched this far beyond the smallest observed resource", 0, low_open=True)
    window_decades: float = setting("compute: outcomes on the envelope this close to the needed compute form the mix",
                                    0, low_open=True)
    report: ReportTargets = setting("the report's targets")


@dataclass(frozen=True)
class Joint:
    """predict's cheapest configuration: the joint law L(p, d, n) = E + A p^-alpha + B d^-beta + C n^-gamma."""

    above_weight: float = setting("a law above an outcome weighs this many times one below", 1)
    huber_delta: float = setting("Huber threshold of the log residuals", 0, low_open=True)
    max_exponent: float = setting("exponents in [0, max_exponent]", 0, low_open=True)
    floor_share: float = setting("E and each term at the smallest size at least this share of the smallest error",
                                 0, 1, low_open=True)
    start_exponents: list[float] = setting("every combination over the terms starts one refinement", 0,
                                           nonempty=True)
    max_evaluations: int = setting("evaluations per refinement", 1)
    tolerance: float = setting("a refinement stops when the loss or theta change by less than this share", 0, 1,
                               low_open=True)
    min_levels: int = setting("a size with fewer distinct values has no term", 2)
    min_configurations: int = setting("fewest configurations a joint law is fitted on", 4)
    bootstrap: int = setting("refits on resampled configurations for the cost interval", 0)
    beyond_doublings: int = setting("candidates: the sweep's values of each size axis and this many doublings", 0, 10)
    backtest_share: float = setting("backtest: fit on the cheapest configurations up to this share of the "
                                    "predicted core-hours", 0, 1, low_open=True, high_open=True)

    def check(self) -> None:
        for exponent in self.start_exponents:
            require_number("nsl.joint.start_exponents value", exponent, 0, self.max_exponent)


@dataclass(frozen=True)
class Learning:
    """Did the models learn (nsl_hpc.analysis.learning): fit's and report's check of each (system, arch)."""

    below: float = setting("a task learned where its nmae is below this times the mean predictor's", 0, 1,
                           low_open=True)
    flag_share: float = setting("a pair is flagged where more than this share of its better-resourced tasks score "
                                "no better than the mean predictor", 0, 1)
    resource: str = setting("the resource that ranks a pair's tasks (one of nsl.resources)")
    above_quantile: float = setting("the better-resourced tasks: those above this quantile of the resource (0: all)",
                                    0, 1, high_open=True)


@dataclass(frozen=True)
class Nsl(FitSettings):
    """Fitting broken NSLs (nsl_hpc.nsl.fit_nsl) to every (system, arch, resource, metric) of a sweep: the search
    (FitSettings' keys) and what is fitted, how sure, what it predicts."""

    resources: dict[str, Resource] = setting("resource -> results column, symbol in formulas, axis label",
                                             nonempty=True)
    metrics: dict[str, str] = setting("results column -> label", nonempty=True)
    K: int = setting("envelope points, log-spaced over the resource range", 2)
    breaks: int | None = setting("a fixed number of breaks b; null: chosen in 0..max_breaks", 0)
    max_breaks: int = setting("the most breaks a law may have", 0)
    bootstrap: int = setting("resamples of the outcomes refitted for intervals (0: none)", 0)
    bootstrap_draw: str = setting("what a resample holds: half, half the outcomes without replacement; "
                                  "replacement, as many drawn with replacement", choices=DRAWS)
    bootstrap_level: float = setting("interval coverage", 0, 1, low_open=True, high_open=True)
    bootstrap_interval: str = setting("basic: reflected about the fit's value; percentile: the quantiles",
                                      choices=INTERVALS)
    predict: Predict = setting("what it takes")
    joint: Joint = setting("predict's joint law")
    backtest_cut: float = setting("extrapolation backtest: fit below this share of the log resource range", 0, 1,
                                  low_open=True, high_open=True)
    learning: Learning = setting("did the models learn: the flag of a pair whose models do not")

    def check(self) -> None:
        super().check()
        if self.max_breaks > self.positions:
            raise ConfigError(f"nsl.max_breaks={self.max_breaks} must be an integer from 0 to {self.positions} "
                              "(nsl.positions)")
        if self.breaks is not None and self.breaks > self.max_breaks:
            raise ConfigError(f"nsl.breaks={self.breaks} must be an integer from 0 to {self.max_breaks} "
                              "(nsl.max_breaks)")
        require_choice("nsl.predict.report.resource", self.predict.report.resource, list(self.resources))
        require_choice("nsl.predict.report.metric", self.predict.report.metric, list(self.metrics))
        require_choice("nsl.learning.resource", self.learning.resource, list(self.resources))


@dataclass(frozen=True)
class Figures:
    """Figures of the NSLs (matplotlib, headless)."""

    formats: list[str] = setting("file formats written", nonempty=True)
    dpi: int = setting("resolution of raster formats", 10, 2400)
    colour: dict[str, str] = setting("NSL resource -> resource that colours the outcomes")
    size: dict[str, str] = setting("NSL resource -> resource that sizes the markers")
    marker_size: list[float] = setting("smallest and largest marker area (points^2)", 0, low_open=True)
    formula_width: int = setting("characters per line of the formula in legends", 20)
    decades_above_envelope: float = setting("the plotted range ends this many decades above the envelope's highest "
                                            "step; outcomes beyond it (diverged free runs) are drawn at its edge",
                                            0, low_open=True)

    def check(self) -> None:
        from matplotlib.figure import Figure  # matplotlib's import is a second of a command's start

        supported = Figure().canvas.get_supported_filetypes()
        for form in self.formats:
            require_choice("figures.formats value", form, list(supported))
        if len(self.marker_size) != 2 or self.marker_size[1] < self.marker_size[0]:
            raise ConfigError(f"figures.marker_size={self.marker_size!r} must be [smallest, largest]")


def nsl_settings(nsl: Mapping[str, Any]) -> Nsl:
    """The ``nsl`` group, typed and checked."""
    return typed(Nsl, nsl, "nsl")


def figure_settings(figures: Mapping[str, Any], resources: Mapping[str, Any]) -> Figures:
    """The ``figures`` group, typed and checked; its colour and size name ``resources``."""
    settings = typed(Figures, figures, "figures")
    for key in ("colour", "size"):
        for resource, other in getattr(settings, key).items():
            require_choice(f"figures.{key}.{resource}", other, list(resources))
    return settings


def check_target(target: Any, metric: str, resource: str, nsl: Nsl) -> None:
    """Raise ConfigError unless ``target`` is a positive finite error of a fitted ``metric`` and ``resource``."""
    require_choice("metric", metric, list(nsl.metrics))
    require_choice("resource", resource, list(nsl.resources))
    require_number("target", target, 0, low_open=True)


@dataclass(frozen=True)
class MlflowSettings:
    """Where and whether post-processing logs to MLflow (conf/report.yaml's ``mlflow``)."""

    enabled: bool = setting("false: write no MLflow runs")
    tracking_uri: str | None = setting("a tracking server or store (null: sqlite:///<sweep_dir>/mlflow.db)")
    experiment: str = setting("the experiment the sweep's runs go in")
    timeout_s: float = setting("a tracking server must answer within this before anything is written (s)", 0, 600,
                               low_open=True)
