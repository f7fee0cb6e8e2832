"""Figures of a sweep's NSLs, like the study's: per NSL a log-log scatter of every outcome (colour and
marker size from other resources, log colour bar), the lower envelope, the fitted law with its breaks, the
formula, M and its bootstrap band, and the published law where the study gives one (dashed); and per
(resource, metric) an overview grid architecture x system. PNG and PDF under
``<sweep_dir>/figures/`` (``nsl/<system>__<arch>__<resource>__<metric>.*``, ``overview__<resource>__<metric>.*``).
"""

import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from matplotlib.axes import Axes
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from nsl_hpc.analysis.bootstrap import band, thetas_of
from nsl_hpc.analysis.broken_law import NSLFit, log_law, lower_envelope
from nsl_hpc.analysis.fitting import fit_from_row, fittable, pair_outcomes
from nsl_hpc.analysis.nsl_settings import Figures, Nsl
from nsl_hpc.analysis.published import KEY as PUBLISHED_KEY
from nsl_hpc.analysis.published import published_law
from nsl_hpc.core.atomic import replacing
from nsl_hpc.core.progress import progress
from nsl_hpc.sweep import layout

REHEARSAL_TITLE = "REHEARSAL, synthetic outcomes: "  # on every figure of a rehearsal
MAX_DECADES_BELOW = 1e3  # a published law further below the outcomes than this factor is named, not drawn in view


def figure_stem(sweep_dir: Path, row: Mapping[str, Any]) -> Path:
    name = f"{row['system']}__{row['arch']}__{row['resource']}__{row['metric']}"
    return Path(sweep_dir) / layout.FIGURES / "nsl" / name


def overview_stem(sweep_dir: Path, resource: str, metric: str) -> Path:
    return Path(sweep_dir) / layout.FIGURES / f"overview__{resource}__{metric}"


def save(fig: Figure, stem: Path, figures: Figures) -> list[Path]:
    """The figure in each of ``figures.formats``, laid out once: the first format's drawing runs the constrained
    layout, the others keep its positions (the layout takes about half of a drawing's time)."""
    paths = []
    for fmt in figures.formats:
        path = stem.with_suffix(f".{fmt}")
        with replacing(path) as temporary:
            fig.savefig(temporary, format=fmt, dpi=figures.dpi)
        fig.set_layout_engine("none")
        paths.append(path)
    return paths


def marker_sizes(values: np.ndarray, limits: Sequence[float]) -> np.ndarray:
    """Marker areas growing with log(value) from limits[0] to limits[1]."""
    logs = np.log(values)
    span = logs.max() - logs.min()
    share = (logs - logs.min()) / span if span > 0 else np.full_like(logs, 0.5)
    return limits[0] + share * (limits[1] - limits[0])


def outcomes_of(results: pa.Table, row: Mapping[str, Any], nsl: Nsl, figures: Figures
                ) -> dict[str, np.ndarray]:
    """Resource, error, colour and size values of the fitted outcomes of one NSL."""
    subset = pair_outcomes(results, row["system"], row["arch"])
    resources = nsl.resources
    columns = {"r": resources[row["resource"]].column, "c": resources[figures.colour[row["resource"]]].column,
               "s": resources[figures.size[row["resource"]]].column}
    keep = fittable(subset, columns["r"], row["metric"])
    values = {name: subset[column].to_numpy().astype(float)[keep] for name, column in columns.items()}
    return {**values, "e": subset[row["metric"]].to_numpy().astype(float)[keep]}


def draw_nsl(ax: Axes, data: Mapping[str, np.ndarray], row: Mapping[str, Any], nsl: Nsl,
             figures: Figures, norm: LogNorm, legend: bool):
    """One NSL on ``ax``; returns the scatter (for a colour bar)."""
    points = ax.scatter(data["r"], data["e"], c=data["c"], s=marker_sizes(data["s"], figures.marker_size),
                        norm=norm, cmap="viridis", alpha=0.6, linewidths=0, rasterized=True)
    grid_r, grid_e = lower_envelope(data["r"], data["e"], nsl.K)
    ax.step(grid_r, grid_e, where="post", color="black", lw=1.2, label=f"envelope (K={nsl.K}, Definition 1)")
    dense = np.geomspace(grid_r[0], grid_r[-1], 400)
    if row["error"] is None:
        fit = fit_from_row(row)
        if row.get("envelope") == "interpolated":  # why the law may run below the steps
            ax.plot(*lower_envelope(data["r"], data["e"], nsl.K, "interpolated"), color="grey", lw=0.9,
                    label="interpolated envelope (the fitted one: the law may run below the steps)")
        formula = "\n".join(textwrap.wrap(row["formula"], figures.formula_width))
        law, determined = fit.predict(dense), determined_mask(dense, fit, row)
        ax.plot(dense, np.where(determined, law, np.nan), color="crimson", lw=1.8,
                label=f"{formula}\nM = {row['margin']:.2g}")
        if not determined.all():  # the segments the outcomes do not determine: no law there
            ax.plot(dense, np.where(np.convolve(~determined, [1, 1, 1], "same") > 0, law, np.nan), color="grey",
                    ls=":", lw=1.5, label="\n".join(textwrap.wrap(f"undetermined: {row['undetermined']}",
                                                                 figures.formula_width)))
        thetas = thetas_of(row)
        if len(thetas):
            low, high = band(fit, thetas, dense, nsl.bootstrap_level, nsl.bootstrap_interval)
            ax.fill_between(dense, low, high, where=determined, color="crimson", alpha=0.15, lw=0,
                            label=f"{nsl.bootstrap_level:.0%} band ({len(thetas)} resamples)")
        for i, (sigma, _, _) in enumerate(fit.breaks):
            ax.axvline(sigma, color="crimson", ls=":", lw=1, label="breaks" if i == 0 else None)
    low = data["e"].min() / 2
    high = min(data["e"].max() * 2, grid_e.max() * 10 ** figures.decades_above_envelope)
    beyond = data["e"] > high
    if beyond.any():  # diverged free runs: at the edge, not stretching the range by decades
        ax.scatter(data["r"][beyond], np.full(beyond.sum(), high / 1.3), marker="^", color="grey", s=18,
                   label=f"{beyond.sum()} beyond the plotted range (up to {data['e'][beyond].max():.2g})")
    published = published_law(tuple(row[k] for k in PUBLISHED_KEY))
    if published is not None:
        on_ours, law = row.get("paper_margin_on_ours"), published.law.predict(dense)
        below = law.max() < low / MAX_DECADES_BELOW
        if not below:
            low = min(low, law.min() / 1.5)
        ax.plot(dense, law, color="darkorange", ls="--", lw=1.8,
                label=f"published (b={published.b}, M={published.margin:.2g}"
                      + ("" if on_ours is None else f"; M on ours {on_ours:.2g}")
                      + (f"; below the plotted range, at {law.min():.2g}-{law.max():.2g}" if below else "") + ")")
    if row.get("planted_theta") is not None:  # a rehearsal: the law its outcomes were drawn from
        ax.plot(dense, np.exp(log_law(np.asarray(row["planted_theta"]), np.log(dense))), color="purple", ls="--",
                lw=1.8, label=f"planted law (rehearsal; M on ours {row['planted_margin_on_ours']:.2g})")
    ax.set_ylim(float(low), float(high))
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis, limits in ((ax.xaxis, (data["r"].min(), data["r"].max())), (ax.yaxis, (low, high))):
        log_ticks(axis, *limits)
    ax.grid(True, which="major", alpha=0.3)
    if legend:
        ax.figure.legend(loc="outside lower center", fontsize=8, ncols=2)
    return points


def determined_mask(r: np.ndarray, fit: NSLFit, row: Mapping[str, Any]) -> np.ndarray:
    """Which resources ``r`` lie in a segment of the law whose slope the outcomes determine (nsl_fits'
    undetermined_segments)."""
    segments = np.searchsorted([sigma for sigma, _, _ in fit.breaks], r)
    return ~np.isin(segments, row.get("undetermined_segments") or [])


def log_ticks(axis, low: float, high: float) -> None:
    """Enough labels on a log axis from ``low`` to ``high``: at every 1..9 x 10^k under half a decade, at 1, 2, 3,
    5, 7 x 10^k under one, at 1, 2, 5 x 10^k under 3, else at 10^k only; never on minor ticks (they collide)."""
    decades = np.log10(high / low)
    if decades < 3:
        subs = ((1.0, 2.0, 5.0) if decades >= 1 else (1.0, 2.0, 3.0, 5.0, 7.0) if decades >= 0.5
                else tuple(float(k) for k in range(1, 10)))
        axis.set_major_locator(LogLocator(base=10, subs=subs))
    axis.set_major_formatter(FuncFormatter(power_label))
    axis.set_minor_formatter(NullFormatter())


SUPERSCRIPT = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079")


def power_label(value: float, _position: object = None) -> str:
    """A tick label 10^k or a x 10^k with Unicode superscripts (mathtext's typesetting took a third of a report)."""
    if value <= 0:
        return ""
    exponent = math.floor(math.log10(value) + 1e-9)
    mantissa = round(value / 10.0 ** exponent, 6)
    power = "10" + str(exponent).translate(SUPERSCRIPT)
    return power if mantissa == 1 else f"{mantissa:g}\u00d7{power}"


def figure_for_nsl(sweep_dir: Path, results: pa.Table, row: Mapping[str, Any], nsl: Nsl,
                   figures: Figures) -> list[Path]:
    data = outcomes_of(results, row, nsl, figures)
    if len(data["r"]) == 0:
        return []
    fig = Figure(figsize=(7.5, 5.2), layout="constrained")
    ax = fig.subplots()
    points = draw_nsl(ax, data, row, nsl, figures, LogNorm(data["c"].min(), data["c"].max()), legend=True)
    colour, size = figures.colour[row["resource"]], figures.size[row["resource"]]
    fig.colorbar(points, ax=ax, label=nsl.resources[colour].label, format=FuncFormatter(power_label))
    ax.set_xlabel(nsl.resources[row["resource"]].label)
    ax.set_ylabel(f"{nsl.metrics[row['metric']]} (test)")
    ax.set_title(f"{REHEARSAL_TITLE if row.get('rehearsal') else ''}{row['system']} / {row['arch']}: "
                 f"{nsl.metrics[row['metric']]} vs {row['resource']} (marker size: {size})", fontsize=10)
    return save(fig, figure_stem(sweep_dir, row), figures)


def overview_figure(sweep_dir: Path, results: pa.Table, rows: Sequence[Mapping[str, Any]], resource: str, metric: str,
                    nsl: Nsl, figures: Figures) -> list[Path]:
    """Architecture (rows) x system (columns) grid of the NSLs of one (resource, metric)."""
    archs = list(dict.fromkeys(row["arch"] for row in rows))
    systems = list(dict.fromkeys(row["system"] for row in rows))
    fig = Figure(figsize=(3.6 * len(systems) + 1, 2.9 * len(archs)), layout="constrained")
    axes = fig.subplots(len(archs), len(systems), squeeze=False, sharex=True)
    data = {(row["system"], row["arch"]): outcomes_of(results, row, nsl, figures) for row in rows}
    colours = np.concatenate([d["c"] for d in data.values() if len(d["c"])] or [np.ones(1)])
    norm, points = LogNorm(colours.min(), colours.max()), None
    for row in rows:
        ax = axes[archs.index(row["arch"]), systems.index(row["system"])]
        if len(data[row["system"], row["arch"]]["r"]):
            points = draw_nsl(ax, data[row["system"], row["arch"]], row, nsl, figures, norm, legend=False)
        fitted = "not fitted" if row["error"] else f"b={row['b']}, M={row['margin']:.2g}"
        ax.set_title(f"{row['system']} / {row['arch']}: {fitted}", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel(nsl.resources[resource].label, fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel(nsl.metrics[metric], fontsize=8)
    if points is not None:
        fig.colorbar(points, ax=axes, label=nsl.resources[figures.colour[resource]].label, shrink=0.8,
                     format=FuncFormatter(power_label))
    # a legend no wider than the panels: two entries a row under one column of panels
    fig.legend(*overview_legend(axes), loc="outside lower center", fontsize=8, ncols=2 if len(systems) == 1 else 4)
    if any(row.get("rehearsal") for row in rows):
        fig.suptitle(REHEARSAL_TITLE.rstrip(": "), color="purple")
    return save(fig, overview_stem(sweep_dir, resource, metric), figures)


def overview_legend(axes: np.ndarray) -> tuple[list, list[str]]:
    """One legend entry per kind of line in the panels (envelope, law, band, breaks, published law, undetermined
    segments): the first panel's of each; the formulas differ per panel and are in each panel's own figure."""
    handles: dict[str, Any] = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            kind = legend_kind(label)
            if kind is not None and kind not in handles:
                handles[kind] = (handle, label.split("(")[0].strip() if kind == "band" else kind)
    return [handle for handle, _ in handles.values()], [label for _, label in handles.values()]


# A panel's label begins so (``draw_nsl``) -> its entry in an overview's legend; the fitted law's label is its
# formula, which ends with its margin
LEGEND_KINDS = {"undetermined": "undetermined segment (no law there)", "interpolated": "interpolated envelope (fitted)",
                "envelope": "lower envelope", "published": "published law", "planted": "planted law (rehearsal)",
                "breaks": "breaks"}


def legend_kind(label: str) -> str | None:
    """The overview legend's entry of a panel's line labelled ``label`` (None: not in the legend); 'band' for the
    bootstrap band."""
    kind = next((entry for start, entry in LEGEND_KINDS.items() if label.startswith(start)), None)
    if kind is None and "band (" in label:
        return "band"
    if kind is None and "\nM = " in label:
        return "fitted law"
    return kind


def draw_figures(sweep_dir: Path, results: pa.Table, rows: list[dict[str, Any]], nsl: Nsl,
                 figures: Figures) -> dict[str, list[Path]]:
    """Every NSL figure and overview grid; returns their paths by kind ('nsl', 'overview')."""
    drawn: dict[str, list[Path]] = {"nsl": [], "overview": []}
    for row in progress(rows, "figures", "NSL"):
        drawn["nsl"] += figure_for_nsl(sweep_dir, results, row, nsl, figures)
    kinds = [(resource, metric) for resource in nsl.resources for metric in nsl.metrics]
    for resource, metric in progress(kinds, "overview figures", "grid"):
        group = [row for row in rows if row["resource"] == resource and row["metric"] == metric]
        if group:
            drawn["overview"] += overview_figure(sweep_dir, results, group, resource, metric, nsl, figures)
    return drawn
