"""The checks of the post-processing settings (``nsl.*``, ``figures.*``, a prediction's target), run before any
work so that a bad value is one line and nothing written is replaced."""

from collections.abc import Mapping
from typing import Any

from matplotlib.figure import Figure

from nsl_hpc.analysis.broken_law import ENVELOPES, OBJECTIVES
from nsl_hpc.errors import ConfigError, require_choice, require_int, require_number


def check_nsl(nsl: Mapping[str, Any]) -> None:
    """Raise ConfigError for an ``nsl`` value no fit, interval or prediction can use."""
    for name, resource in nsl["resources"].items():
        if not isinstance(resource, Mapping) or not {"column", "symbol", "label"} <= set(resource):
            raise ConfigError(f"nsl.resources.{name}={resource!r} must be a mapping with column, symbol and label")
    if not nsl["metrics"]:
        raise ConfigError("nsl.metrics is empty; name at least one results column, e.g. {nmae: nMAE}")
    require_int("nsl.K", nsl["K"], 2)
    require_int("nsl.positions", nsl["positions"], 1)
    require_int("nsl.max_breaks", nsl["max_breaks"], 0, nsl["positions"])
    if nsl["breaks"] is not None:
        require_int("nsl.breaks", nsl["breaks"], 0, nsl["max_breaks"])
    require_choice("nsl.objective", nsl["objective"], OBJECTIVES)
    require_choice("nsl.envelope", nsl["envelope"], ENVELOPES)
    require_int("nsl.starts", nsl["starts"], 1)
    require_int("nsl.random_starts", nsl["random_starts"], 0)
    require_int("nsl.finalists", nsl["finalists"], 1)
    for share in nsl["alpha_shares"]:
        require_number("nsl.alpha_shares value", share, 0, 1, high_open=True)
    require_number("nsl.max_slope", nsl["max_slope"], 0, low_open=True)
    require_number("nsl.max_rise", nsl["max_rise"], 0, nsl["max_slope"])
    require_int("nsl.min_segment_points", nsl["min_segment_points"], 1)
    require_number("nsl.edge", nsl["edge"], 0, 0.5, high_open=True)
    require_number("nsl.phi_min", nsl["phi_min"], 0, low_open=True)
    require_number("nsl.min_gain", nsl["min_gain"], 0, 1, high_open=True)
    require_number("nsl.choice_trim", nsl["choice_trim"], 0, 1, high_open=True)
    require_number("nsl.margin_floor", nsl["margin_floor"], 0)
    require_number("nsl.study_beta", nsl["study_beta"], 0)
    if nsl["study_phi"] is not None:
        require_number("nsl.study_phi", nsl["study_phi"], nsl["phi_min"])
    require_int("nsl.study_steps", nsl["study_steps"], 1)
    require_number("nsl.study_lr", nsl["study_lr"], 0, low_open=True)
    require_int("nsl.bootstrap", nsl["bootstrap"], 0)
    require_number("nsl.bootstrap_level", nsl["bootstrap_level"], 0, 1, low_open=True, high_open=True)
    require_choice("nsl.bootstrap_interval", nsl["bootstrap_interval"], ["basic", "percentile"])
    require_number("nsl.backtest_cut", nsl["backtest_cut"], 0, 1, low_open=True, high_open=True)
    check_joint(nsl["joint"])
    predict = nsl["predict"]
    require_number("nsl.predict.decades", predict["decades"], 0, low_open=True)
    require_number("nsl.predict.window_decades", predict["window_decades"], 0, low_open=True)
    require_choice("nsl.predict.report.resource", predict["report"]["resource"], list(nsl["resources"]))
    require_choice("nsl.predict.report.metric", predict["report"]["metric"], list(nsl["metrics"]))
    if not predict["report"]["factors"]:
        raise ConfigError("nsl.predict.report.factors is empty; give at least one factor, e.g. [1.0]")
    for factor in predict["report"]["factors"]:
        require_number("nsl.predict.report.factors value", factor, 0, low_open=True)


def check_joint(joint: Mapping[str, Any]) -> None:
    """Raise ConfigError for an ``nsl.joint`` value no joint law can be fitted or searched with."""
    require_number("nsl.joint.above_weight", joint["above_weight"], 1)
    require_number("nsl.joint.huber_delta", joint["huber_delta"], 0, low_open=True)
    require_number("nsl.joint.max_exponent", joint["max_exponent"], 0, low_open=True)
    require_number("nsl.joint.floor_share", joint["floor_share"], 0, 1, low_open=True)
    if not joint["start_exponents"]:
        raise ConfigError("nsl.joint.start_exponents is empty; give at least one, e.g. [0.3, 1.0]")
    for exponent in joint["start_exponents"]:
        require_number("nsl.joint.start_exponents value", exponent, 0, joint["max_exponent"])
    require_int("nsl.joint.max_evaluations", joint["max_evaluations"], 1)
    require_number("nsl.joint.tolerance", joint["tolerance"], 0, 1, low_open=True)
    require_int("nsl.joint.min_levels", joint["min_levels"], 2)
    require_int("nsl.joint.min_configurations", joint["min_configurations"], 4)
    require_int("nsl.joint.bootstrap", joint["bootstrap"], 0)
    require_int("nsl.joint.beyond_doublings", joint["beyond_doublings"], 0, 10)
    require_number("nsl.joint.backtest_share", joint["backtest_share"], 0, 1, low_open=True, high_open=True)


def check_figures(figures: Mapping[str, Any], resources: Mapping[str, Any]) -> None:
    """Raise ConfigError for a ``figures`` value no figure can be drawn with."""
    supported = Figure().canvas.get_supported_filetypes()
    if not figures["formats"]:
        raise ConfigError("figures.formats is empty; choose from: " + ", ".join(supported))
    for form in figures["formats"]:
        require_choice("figures.formats value", form, list(supported))
    require_int("figures.dpi", figures["dpi"], 10, 2400)
    for key in ("colour", "size"):
        for resource, other in figures[key].items():
            require_choice(f"figures.{key}.{resource}", other, list(resources))
    sizes = figures["marker_size"]
    if len(sizes) != 2:
        raise ConfigError(f"figures.marker_size={list(sizes)!r} must be [smallest, largest]")
    require_number("figures.marker_size[0]", sizes[0], 0, low_open=True)
    require_number("figures.marker_size[1]", sizes[1], sizes[0])
    require_int("figures.formula_width", figures["formula_width"], 20)


def check_target(target: Any, metric: str, resource: str, nsl: Mapping[str, Any]) -> None:
    """Raise ConfigError unless ``target`` is a positive finite error of a fitted ``metric`` and ``resource``."""
    require_choice("metric", metric, list(nsl["metrics"]))
    require_choice("resource", resource, list(nsl["resources"]))
    require_number("target", target, 0, low_open=True)
