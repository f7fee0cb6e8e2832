"""The self-contained report.html of a sweep: its tables, fits and figures."""


import base64
import html
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from nsl_hpc.analysis.fitting import fit_note, last_slope_undetermined, nsl_key
from nsl_hpc.analysis.learning import PairLearning
from nsl_hpc.analysis.nsl_settings import Learning, Nsl, ReportTargets
from nsl_hpc.analysis.prediction import format_need
from nsl_hpc.config import compose_config, plain
from nsl_hpc.config.identity import outcome_values
from nsl_hpc.config.mapping import flatten
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.grid import sub_grids
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.manifest import read_base_config
from nsl_hpc.sweep.merge import MergeSummary

STYLE = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px;text-align:left}
th{background:#f2f2f2}code{font-size:12px}img{max-width:100%}pre{background:#f7f7f7;padding:.6em}"""


def embedded_png(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def cells(values: Sequence[Any]) -> str:
    return "".join(f"<td>{html.escape(str(v))}</td>" for v in values)


def interval(row: Mapping[str, Any], name: str, digits: str = ".2f") -> str:
    """'point [low, high]' of a bootstrapped quantity, '' when not bootstrapped."""
    if row.get(f"{name}_lo") is None:
        return "" if row.get(name) is None else format(row[name], digits)
    return f"{row[name]:{digits}} [{row[f'{name}_lo']:{digits}}, {row[f'{name}_hi']:{digits}}]"


def last_slope_cell(row: Mapping[str, Any]) -> str:
    """The last slope with its interval, or 'undetermined' with the slope the fit stopped at."""
    if last_slope_undetermined(row):
        return f"undetermined ({row['last_slope']:.2f})"
    return interval(row, "last_slope")


def slopes_cell(row: Mapping[str, Any]) -> str:
    """Each segment's slope with the outcomes of the envelope it stands on, '?' marking an undetermined one."""
    undetermined = set(row.get("undetermined_segments") or [])
    return ", ".join(f"{slope:.2f}{'?' if k in undetermined else ''} ({n})"
                     for k, (slope, n) in enumerate(zip(row["slopes"], row["segment_points"], strict=True)))


def core_hours_line(core_hours: Mapping[str, Any]) -> str:
    """The merged tasks' predicted and measured core-hours, in one sentence."""
    measured = core_hours["measured"]
    return (f"Their core-hours: {core_hours['predicted']:.3g} predicted by the planner, "
            + ("not measured (rows without wall_seconds)." if measured is None else
               f"{measured:.3g} measured ({measured / core_hours['predicted']:.2f}x)."
               if core_hours["predicted"] else f"{measured:.3g} measured."))


def nsl_table(rows: Sequence[Mapping[str, Any]]) -> str:
    head = ("<tr><th>system</th><th>arch</th><th>resource</th><th>metric</th><th>outcomes</th><th>b</th>"
            "<th>M</th><th>slopes (outcomes of the envelope; ? undetermined)</th><th>last slope [90%]</th>"
            "<th>backtest M</th><th>law</th></tr>")
    body = []
    for row in rows:
        fitted = row["error"] is None
        backtest = row.get("backtest_margin")
        body.append("<tr>" + cells((
            row["system"], row["arch"], row["resource"], row["metric"], f"{row['outcomes']:,}",
            row["b"] if fitted else "", f"{row['margin']:.2g}" if fitted else "",
            slopes_cell(row) if fitted else "", last_slope_cell(row) if fitted else "",
            f"{backtest:.2g}" if fitted and backtest is not None else "")) +
            f"<td><code>{html.escape(row['formula'] if fitted else 'not fitted: ' + row['error'])}</code></td></tr>")
    return f"<table>{head}{''.join(body)}</table>"


COMPARISON_HEAD = ("NSL", "b paper / ours", "M paper / ours", "published law's M on our envelope",
                   "M by b paper / ours (fitted envelope)", "last slope paper / ours [90%]", "breaks paper",
                   "breaks ours [90%]", "resources paper / ours", "in the paper")
MISSING = "—"


def number(value: Any, digits: str) -> str:
    return MISSING if value is None else format(value, digits)


def comparison_rows(rows: Sequence[Mapping[str, Any]]) -> list[tuple[str, ...]]:
    """The cells (COMPARISON_HEAD) of paper vs ours for every fitted NSL the study publishes a law (or only
    margins by b) for, one meaning per column, MISSING where a side has no value; resources: the study grid's
    range, ours the range of the fitted outcomes."""
    table: list[tuple[str, ...]] = []
    for row in rows:
        if row["error"] is not None or (row.get("paper_b") is None and row.get("paper_margins_by_b") is None):
            continue
        paper_breaks = json.loads(row["paper_breaks"]) if row.get("paper_breaks") else None
        paper_range = json.loads(row["paper_range"]) if row.get("paper_range") else None
        by_b = MISSING
        if row.get("paper_margins_by_b") is not None:
            published, ours = json.loads(row["paper_margins_by_b"]), json.loads(row["margins_by_b"])
            by_b = "; ".join(f"b={b}: {m:.2g} / {number(ours.get(b), '.2g')}" for b, m in published.items())
        table.append((
            " / ".join(row[k] for k in ("system", "arch", "resource", "metric")),
            f"{number(row.get('paper_b'), 'd')} / {row['b']}",
            f"{number(row.get('paper_margin'), '.2g')} / {row['margin']:.2g}",
            number(row.get("paper_margin_on_ours"), ".2g"),
            by_b,
            f"{number(row.get('paper_last_slope'), '.2f')} / {last_slope_cell(row) or MISSING}",
            MISSING if paper_breaks is None else ", ".join(f"{sigma:.2g}" for sigma in paper_breaks) or "none",
            ", ".join(interval(row, f"sigma_{i}", ".2g") for i in range(1, row["b"] + 1)) or "none",
            f"{MISSING if paper_range is None else f'{paper_range[0]:.2g}-{paper_range[1]:.2g}'} / "
            f"{row['r_min']:.2g}-{row['r_max']:.2g}",
            row.get("paper_where") or "Appendix (margins by b)"))
    return table


NORMALIZATION_NOTES = {
    "scalar": "nMAE and nMSE divide every dx/dt column by one spread of the whole test matrix (the authors' code)",
    "per_column": "nMAE and nMSE divide each dx/dt column by its own spread (the paper's formula)",
}


def scores_note(study: str, normalization: str | None) -> str:
    """Which normalisation (``metric.normalization``; None: a format-1 sweep's) the sweep's nmae / nmse columns
    (and so the comparison) use; '' for the input-output study, whose scores are of one output column (both
    normalisations agree)."""
    if study != "input_state":
        return ""
    if normalization is None:  # a format-1 sweep (nsl_hpc/sweep/formats.py), before either could be chosen
        return "Scores: nMAE and nMSE per dx/dt column (a sweep from before metric.normalization)."
    return (f"Scores: {NORMALIZATION_NOTES[normalization]} (metric.normalization={normalization}); every row also "
            "holds the other pair (nmae_per_column, nmae_scalar, ...: fit metrics=[...] fits them).")


def rehearsal_html(rows: Sequence[Mapping[str, Any]]) -> str:
    """A rehearsal's banner and its planted laws beside the fitted ones ('' for a real sweep)."""
    planted = [row for row in rows if row.get("planted_formula") is not None]
    if not any(row.get("rehearsal") for row in rows):
        return ""
    recovered = sum(bool(row.get("planted_recovered")) for row in planted)
    body = "".join("<tr>" + cells((
        nsl_key(row).replace("/", " / "), row["planted_formula"], f"{row['planted_last_slope']:.2f}",
        last_slope_cell(row) if row["error"] is None else "not fitted", f"{row['planted_L_at_max']:.3g}",
        interval(row, "L_at_max", ".3g") if row["error"] is None else "", f"{row['planted_envelope_excess']:.3f}",
        f"{row['planted_margin_on_ours']:.2g}",
        {True: "yes", False: "no", None: "no intervals"}[row.get("planted_recovered")])) + "</tr>"
        for row in planted)
    return ('<p style="color:purple"><b>REHEARSAL: no model was trained.</b> Every outcome was drawn from a planted '
            "law (nsl_hpc/sweep/rehearsal.py, rehearse.* of launch.yaml) and faults were planted at the study's rates; "
            f"the laws below are fitted to those draws. {recovered} of {len(planted)} planted laws recovered (the "
            "planted slope and value at the largest resource inside the fit's 90% intervals of its last slope and "
            "value there; an envelope of finite draws lies above the law it bounds: its excess is listed).</p>"
            "<table><tr><th>NSL</th><th>planted law</th><th>planted last slope</th><th>fitted [90%]</th>"
            "<th>planted L(r_max)</th><th>fitted [90%]</th><th>envelope / planted at r_max</th>"
            "<th>planted law's M on the envelope</th>"
            f"<th>recovered</th></tr>{body}</table>")


def comparison_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """Paper vs ours (``comparison_rows``) as an HTML table."""
    body = "".join(f"<tr>{cells(row)}</tr>" for row in comparison_rows(rows))
    if not body:
        return "<p>The study publishes no law for the NSLs of this sweep.</p>"
    return f"<table><tr>{''.join(f'<th>{html.escape(name)}</th>' for name in COMPARISON_HEAD)}</tr>{body}</table>"


def comparison_markdown(rows: Sequence[Mapping[str, Any]], note: str) -> str:
    """Paper vs ours (``comparison_rows``) as a Markdown table (``<sweep_dir>/comparison.md``), ``note`` (which
    scores) after it."""
    lines = ["| " + " | ".join(COMPARISON_HEAD) + " |", "|" + "---|" * len(COMPARISON_HEAD)]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in comparison_rows(rows)]
    if len(lines) == 2:
        return "The study publishes no law for the NSLs of this sweep.\n"
    return "\n".join(lines) + (f"\n\n{note}\n" if note else "\n")


def what_it_takes_html(entries: Sequence[Mapping[str, Any]], settings: ReportTargets, symbol: str) -> str:
    """The report's table of what_it_takes entries (for the targets ``settings``: nsl.predict.report)."""
    head = (f"<tr><th>system</th><th>arch</th><th>target {settings.metric}</th><th>best observed</th>"
            f"<th>{symbol} needed [90%]</th><th>smallest model / data on the envelope there</th></tr>")
    body = "".join("<tr>" + cells((
        entry["system"], entry["arch"], f"{entry['target']:.3g}", f"{entry['best']:.3g}",
        format_need(entry["need"], entry["best"]),
        f"{entry['model']:,.0f} parameters / {entry['data']:,.0f} points" if "model" in entry else "")) + "</tr>"
        for entry in entries)
    factors = ", ".join(f"{factor:g}" for factor in settings.factors)
    return (f"<p>The {settings.resource} each law needs to reach {factors} &times; the best "
            f"{settings.metric} observed for its (system, arch) (<code>python -m nsl_hpc.predict</code> "
            f"answers for any target).</p><table>{head}{body}</table>")


def science_settings(sweep_dir: Path, launch: LaunchSettings) -> dict[tuple[str, str], dict[str, tuple[str, str]]]:
    """Per (system, arch) of the sweep, its outcome-changing settings (the study's shared keys, flattened) as
    (value, the study's default value): what the sweep trained against the Fidelity section's defaults."""
    study = study_named(launch.study.name)
    settings = {}
    for part in sub_grids(launch.sweep.grid):
        for system in part["system"]:
            for arch in part["arch"]:
                used = read_base_config(sweep_dir, system, arch)
                default = plain(compose_config(
                    [f"study={study.name}", f"system={system}", f"arch={arch}"]))
                flat_used = flatten(outcome_values({key: used[key] for key in study.shared_keys}))
                flat_default = flatten(outcome_values({key: default[key] for key in study.shared_keys}))
                settings[system, arch] = {key: (value, flat_default.get(key, "(none)"))
                                          for key, value in flat_used.items()}
    return settings


def configuration_html(settings: Mapping[tuple[str, str], Mapping[str, tuple[str, str]]]) -> str:
    """The settings a sweep trained with: its draws, MLP block, architecture options, loss and training, and
    every value that differs from the study's configuration (docs/fidelity.md)."""
    first = next(iter(settings.values()))
    shown = [key for key in first
             if key.split(".")[0] in ("draws", "train", "metric") or key.startswith("system.test_set.")]
    rows = "".join(f"<tr><th>{html.escape(key)}</th><td>{html.escape(first[key][0])}</td></tr>" for key in shown)
    rows += "".join(f"<tr><th>{html.escape(arch)}</th><td>" + html.escape(", ".join(
        f"{key.removeprefix('arch.')}={value}" for key, (value, _) in pair.items()
        if key.startswith("arch.") and key not in ("arch.name", "arch.study"))) + "</td></tr>"
        for arch, pair in {arch: pair for (_, arch), pair in settings.items()}.items())
    changed = sorted({f"{key}={value} (the study's: {default})" for pair in settings.values()
                      for key, (value, default) in pair.items() if value != default})
    verdict = ("<p>These are the study's settings (docs/fidelity.md).</p>" if not changed else
               "<p>Settings that differ from the study's (docs/fidelity.md):</p><ul>"
               + "".join(f"<li><code>{html.escape(line)}</code></li>" for line in changed) + "</ul>")
    return f"<table>{rows}</table>{verdict}"


def learning_html(pairs: Sequence[PairLearning], settings: Learning) -> str:
    """The report's table of how each (system, arch) learned (``analysis.learning``), flagged pairs in red."""
    if not pairs:
        return ("<p>The rows carry no mean predictor's score (<code>mean_predictor_nmae</code>): a sweep from before "
                "it was recorded.</p>")
    head = ("<tr><th>system</th><th>arch</th><th>no better than the mean predictor</th>"
            "<th>... of the better-resourced</th><th>worst task</th><th></th></tr>")
    body = "".join(
        ('<tr style="color:#b00">' if pair.flagged else "<tr>") + cells((
            pair.system, pair.arch, f"{pair.not_learned:,} of {pair.tasks:,} ({pair.share:.0%})",
            f"{pair.not_learned_above:,} of {pair.above:,} ({pair.share_above:.0%})", pair.worst,
            f"NOT LEARNING: its laws describe models that fail; {pair.why}" if pair.flagged else "")) + "</tr>"
        for pair in pairs)
    return (f"<p>A task did not learn where its nMAE is not below {settings.below:g} times the mean predictor's "
            f"(the constant output at its training data's mean) or it did not finish with finite scores. A pair is "
            f"flagged where more than {settings.flag_share:.0%} of its better-resourced tasks (above the "
            f"{settings.above_quantile:g} quantile of its {settings.resource}) did not learn "
            f"(<code>nsl.learning</code>).</p>"
            f"<table>{head}{body}</table>")


def report_html(sweep_dir: Path, launch: LaunchSettings, summary: MergeSummary, rows: Sequence[Mapping[str, Any]],
                drawn: Mapping[str, list[Path]], what_it_takes: str, nsl: Nsl, core_hours: Mapping[str, Any],
                learning: Sequence[PairLearning], scores: str) -> str:
    """The report's HTML (``drawn``: draw_figures' paths by kind; ``scores``: scores_note's line)."""
    grid = launch.sweep.grid
    parts = sub_grids(grid)
    axes = "".join((f"<tr><th colspan='2'>sub-grid {index + 1} of {len(parts)}</th></tr>" if len(parts) > 1 else "")
                   + "".join(f"<tr><th>{html.escape(axis)}</th><td>{html.escape(', '.join(map(str, values)))}</td></tr>"
                             for axis, values in part.items())
                   for index, part in enumerate(parts))
    overviews = "".join(f"<h3>{html.escape(path.stem.replace('overview__', '').replace('__', ' / '))}</h3>"
                        + embedded_png(path, path.stem) for path in drawn["overview"] if path.suffix == ".png")
    singles = "".join(f"<details><summary>{html.escape(path.stem.replace('__', ' / '))}</summary>"
                      f"{embedded_png(path, path.stem)}</details>" for path in drawn["nsl"] if path.suffix == ".png")
    name = html.escape(launch.sweep.name)
    return f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>NSL report: {name}</title>
<style>{STYLE}</style></head><body>
<h1>Neural scaling laws: {"rehearsal" if launch.rehearsal else "sweep"} {name}</h1>
{rehearsal_html(rows)}
<p>Sweep directory <code>{html.escape(str(Path(sweep_dir).resolve()))}</code>, sweep seed {launch.sweep_seed},
{summary.tasks:,} tasks.</p>
<h2>Grid</h2><table>{axes}</table>
<h2>Configuration</h2>{configuration_html(science_settings(sweep_dir, launch))}
<h2>Tasks</h2><p>{summary.merged:,} tasks merged. {html.escape(core_hours_line(core_hours))}</p>
<pre>{html.escape(summary.describe())}</pre>
<h2>Did the models learn?</h2>{learning_html(learning, nsl.learning)}
<h2>Neural scaling laws ({sum(r['error'] is None for r in rows)} of {len(rows)} fitted)</h2>
<p>L(r) = &alpha; + &beta; r<sup>&delta;0</sup> &prod;<sub>i</sub>
[1 + (r/&sigma;<sub>i</sub>)<sup>1/&phi;<sub>i</sub></sup>]<sup>&delta;<sub>i</sub>&phi;<sub>i</sub></sup>
fitted to the lower envelope of the outcomes; M = mean<sub>k</sub>
(ln L(r~<sub>k</sub>) &minus; ln E(r~<sub>k</sub>))<sup>2</sup> on Definition 1's envelope; last slope =
&delta;0 + &Sigma; &delta;<sub>i</sub> with its 90% interval from refits on resampled tasks (given b); backtest M:
the law fitted below the middle of the log resource range, scored above it. {html.escape(fit_note(nsl))}
Each law's card, <code>law_cards/&lt;system&gt;__&lt;arch&gt;__&lt;resource&gt;__&lt;metric&gt;.json</code>, holds
what it takes to reproduce or reject it (grid and hash, envelope points, b and why, intervals, backtest, the
published law, code version).</p>
{nsl_table(rows)}
<h2>Against the published laws</h2>
<p>The study's laws (<code>conf/published_laws.yaml</code>) beside ours where it publishes one: a published M and
ours are each on their own outcomes; the published law's M on our envelope says how well it describes ours. Break
positions are &sigma;<sub>i</sub>; ours with their 90% intervals. {html.escape(scores)}
{html.escape(fit_note(nsl))}</p>
{comparison_table(rows)}
<h2>What it takes</h2>{what_it_takes}
<h2>Overview</h2>{overviews}
<h2>Every NSL</h2>{singles}
</body></html>
"""
