"""Where a reproduction stands against every published law: one entry per law (``LawStatus``), collected from the
merged sweeps of its slice, and the Markdown status table written from those entries alone, so that the table in the
docs can be regenerated from the committed numbers (``benchmarks/reproduction_status.py``).

The published laws are best-of-N statistics: an envelope is the least error over a pair's tasks, so its level
depends on how many tasks it takes. Each entry says how far the envelope rises when built from half of the slice's
tasks (the median over ``halves`` random halves, at each resource)."""

import datetime
import json
import math
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from nsl_hpc.analysis.fitting import pair_outcomes
from nsl_hpc.analysis.learning import MEAN_PREDICTOR, learned
from nsl_hpc.analysis.published import gap_to_published, resource_columns, step_envelope_at
from nsl_hpc.config.schema import setting
from nsl_hpc.sweep import layout

BEGIN, END = "<!-- status table: begin -->", "<!-- status table: end -->"
FIGURES_BEGIN, FIGURES_END = "<!-- law figures: begin -->", "<!-- law figures: end -->"


@dataclass(frozen=True)
class LawSlice:
    """A published law's entry of conf/reproduction.yaml's ``laws``: the slice that measures it and the resources
    its factors are taken at; a law no slice covers says why."""

    at: list[float] = setting("the resources at which our envelope is set over the law", 0, low_open=True,
                              nonempty=True)
    slice: str | None = setting("the slice that measures it (<root>/<slice>; null: none)", default=None)
    why: str = setting("why no slice measures it", default="its slice was not run")
    decided_by: str = setting("what decides the gap, and the committed slice that measured it", default="")


@dataclass(frozen=True)
class LawStatus:
    """One published law: the slice it was measured on (None: not run, ``why``), when, its outcomes, our envelope
    over the law at ``at``, the largest factor either way over them, and each candidate's largest factor."""

    law: str  # system/arch/resource/metric
    at: list[float]
    slice: str | None = None
    measured: str | None = None  # the date the slice's results were read
    outcomes: int = 0
    factors: list[float] = field(default_factory=list)
    largest: float = math.nan
    candidates: dict[str, float] = field(default_factory=dict)
    candidates_on: str = ""  # where the candidates were measured: the slice, or make mechanisms' slices
    why: str = ""
    half_tasks: list[float] = field(default_factory=list)  # at ``at``: the median envelope of half the tasks over
    # the envelope of all (NaN where a half holds no outcome at or below the resource)
    decided_by: str = ""

    def best(self) -> tuple[str, float] | None:
        """The candidate whose largest factor is smallest, None without candidates."""
        known = {name: value for name, value in self.candidates.items() if not math.isnan(value)}
        return min(known.items(), key=lambda item: item[1]) if known else None


def largest_factor(ratios: np.ndarray) -> float:
    """The largest factor between envelope and law, either way, over the resources that have an envelope."""
    known = ratios[~np.isnan(ratios)]
    return float(np.max(np.maximum(known, 1 / known))) if len(known) else math.nan


def law_outcomes(sweep_dir: Path, law: str, column: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(resources, errors) (n,) of one law's finished outcomes on a merged sweep (its rows of the law's pair with a
    finite positive error), the errors of the results ``column`` (None: the law's metric)."""
    system, arch, resource, metric = law.split("/")
    metric = column or metric
    table = pq.read_table(sweep_dir / layout.RESULTS)
    rows = [row for row in table.to_pylist() if (row["system"], row["arch"], row["status"]) == (system, arch, "ok")]
    r = np.array([row[resource_columns()[resource]] for row in rows], dtype=float)
    e = np.array([row[metric] for row in rows], dtype=float)
    keep = np.isfinite(e) & (e > 0)
    return r[keep], e[keep]


def envelope_factors(sweep_dir: Path, law: str, at: Sequence[float], column: str | None = None
                     ) -> tuple[int, np.ndarray]:
    """(outcomes, envelope / law at ``at``) of one law on a merged sweep (``law_outcomes``)."""
    r, e = law_outcomes(sweep_dir, law, column)
    return len(r), gap_to_published(tuple(law.split("/")), r, e, np.asarray(at, dtype=float))


def half_task_rise(r: np.ndarray, e: np.ndarray, at: Sequence[float], halves: int, seed: int = 0) -> np.ndarray:
    """At each resource of ``at`` (m,), the geometric mean over ``halves`` random halves of the outcomes (r, e) (n,)
    of the half's step envelope over the envelope of all: how much an envelope of half the tasks rises, on average
    (a median would read 1 wherever the best outcome is alone: half the halves hold it). NaN where the halves hold
    no outcome at or below it."""
    points = np.asarray(at, dtype=float)
    full = step_envelope_at(r, e, points)
    rng = np.random.default_rng(seed)
    rises = [step_envelope_at(r[kept], e[kept], points) / full
             for kept in (rng.permutation(len(r))[:len(r) // 2] for _ in range(halves))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a resource no half reaches: NaN, as documented
        return np.exp(np.nanmean(np.log(np.array(rises)), axis=0)) if rises else np.full(len(points), math.nan)


def collect(laws: Mapping[str, LawSlice], root: Path, candidates: Mapping[str, Mapping[str, str]],
            mechanism_factors: Mapping[str, dict[str, float]], before: Mapping[str, LawStatus],
            halves: int) -> list[LawStatus]:
    """Each law's status from ``root``/<slice> (and ``root``/<slice>__<candidate> for the slice's ``candidates``;
    ``mechanism_factors``: law -> candidate -> largest factor, from the mechanism table; ``halves``: random halves
    of ``half_task_rise``); a law whose slice is not under ``root`` keeps its entry of ``before`` (with its
    config's ``decided_by``), or is not run, with its config's ``why``; a candidate not under ``root`` keeps its
    factor of ``before``."""
    today = datetime.date.today().isoformat()
    statuses = []
    for law, spec in laws.items():
        at = [float(value) for value in spec.at]
        if not spec.slice or not (root / spec.slice / layout.RESULTS).exists():
            kept = before.get(law)
            statuses.append(replace(kept, decided_by=spec.decided_by) if kept else
                            LawStatus(law, at, why=spec.why, decided_by=spec.decided_by))
            continue
        sweep_dir = root / spec.slice
        r, e = law_outcomes(sweep_dir, law)
        outcomes, ratios = len(r), gap_to_published(tuple(law.split("/")), r, e, np.asarray(at))
        scored, where = dict(mechanism_factors.get(law, {})), "make mechanisms" if law in mechanism_factors else ""
        kept = before.get(law)
        for name in candidates.get(spec.slice, {}):
            other = root / f"{spec.slice}__{name}"
            if (other / layout.RESULTS).exists():
                scored[name], where = largest_factor(envelope_factors(other, law, at)[1]), spec.slice
            elif kept is not None and name in kept.candidates:  # measured before, not on this machine
                scored[name], where = kept.candidates[name], kept.candidates_on
        statuses.append(LawStatus(law, at, spec.slice, today, outcomes, [float(x) for x in ratios],
                                  largest_factor(ratios), scored, where,
                                  half_tasks=[float(x) for x in half_task_rise(r, e, at, halves)],
                                  decided_by=spec.decided_by))
    return statuses


def candidates_table(laws: Mapping[str, LawSlice], root: Path, candidates: Mapping[str, Mapping[str, Sequence[str]]],
                     below: float, before: str = "") -> str:
    """Per slice with candidates, a Markdown table of its default run and each candidate run under ``root``: the
    overrides, the outcomes, how many learned (nMAE below ``below`` times the mean predictor's) and, per law of the
    slice, the envelope over the law at its resources and the largest factor ('' where no slice has candidates). A
    run not under ``root`` keeps its row of ``before`` (the table as committed), else it is said not run."""
    lines: list[str] = []
    for slice_name, runs in candidates.items():
        slice_laws = [law for law, spec in laws.items() if spec.slice == slice_name]
        for law in slice_laws:
            at = [float(value) for value in laws[law].at]
            heading = f"**{law}** on `{slice_name}` (envelope / published law)"
            committed = before.split(heading, 1)[1].split("\n\n**", 1)[0] if heading in before else ""
            lines += [heading, "", "| settings | outcomes | learned | " + " | ".join(map(resource_text, at))
                      + " | largest factor |", "|---|---:|---:|" + "---:|" * (len(at) + 1)]
            for name, overrides in {"default": [], **runs}.items():
                sweep_dir = root / (slice_name if name == "default" else f"{slice_name}__{name}")
                label = f"{name}" + (f" (`{' '.join(overrides)}`)" if overrides else "")
                if not (sweep_dir / layout.RESULTS).exists():
                    kept = [line for line in committed.splitlines() if line.startswith(f"| {label} |")]
                    lines.append(kept[0] if kept else f"| {label} | not run | | " + " | ".join("" for _ in at) + " | |")
                    continue
                pair = pair_outcomes(pq.read_table(sweep_dir / layout.RESULTS), *law.split("/")[:2])
                ratios = envelope_factors(sweep_dir, law, at)[1]
                scored = MEAN_PREDICTOR in pair.column_names and pair[MEAN_PREDICTOR].null_count == 0
                cells = [f"{int(learned(pair, below).sum()):,}" if scored else "- (no mean predictor's score)",
                         *(factor_text(x) for x in ratios), factor_text(largest_factor(ratios))]
                lines.append(f"| {label} | {pair.num_rows:,} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


@dataclass(frozen=True)
class GapReading:
    """One reading of a law's gap (conf/reproduction.yaml's ``gaps``): a slice's envelope over the law, of its tasks
    up to each value of the coordinate ``by`` (``up_to``; none: all its tasks), or with model size read as the
    paper's approximate count (``paper_count``: p = 4 n_d n_h^2, Section 4.1)."""

    slice: str = setting("the slice (<root>/<slice>)")
    label: str = setting("what it changes, as the table names it")
    by: str | None = setting("a coordinate of its rows (e.g. epochs) whose values it is cut at", default=None)
    up_to: list[float] = setting("the values of ``by``: one row of the table each", default_factory=list)
    paper_count: bool = setting("model size as 4 n_d n_h^2 (the rows' depth and width)", default=False)


@dataclass(frozen=True)
class LawGap:
    """A law's readings and the resources they are taken at."""

    at: list[float] = setting("the resources of the table", 0, low_open=True, nonempty=True)
    readings: list[GapReading] = setting("the slices that decide the gap, one thing changed at a time",
                                         nonempty=True)


def reading_outcomes(sweep_dir: Path, law: str, reading: GapReading) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(row label, resources, errors) of each row of one reading of ``law`` on the merged slice ``sweep_dir``."""
    system, arch, resource, metric = law.split("/")
    table = pair_outcomes(pq.read_table(sweep_dir / layout.RESULTS), system, arch)
    ok = np.asarray(table["status"].to_pylist()) == "ok"
    e = table[metric].to_numpy(zero_copy_only=False).astype(float)
    if reading.paper_count:
        r = 4.0 * table["depth"].to_numpy().astype(float) * table["width"].to_numpy().astype(float) ** 2
    else:
        r = table[resource_columns()[resource]].to_numpy(zero_copy_only=False).astype(float)
    keep = ok & np.isfinite(e) & (e > 0)
    if reading.by is None:
        return [(reading.label, r[keep], e[keep])]
    by = table[reading.by].to_numpy(zero_copy_only=False).astype(float)
    return [(f"{reading.label}, {reading.by} <= {value:g}", r[keep & (by <= value)], e[keep & (by <= value)])
            for value in reading.up_to]


def gaps_table(gaps: Mapping[str, LawGap], root: Path) -> str:
    """Markdown: per law, a table of its readings (a row each: the outcomes, the best error, our step envelope over
    the law at the law's resources); a slice not under ``root`` is said not run."""
    lines: list[str] = []
    for law, gap in gaps.items():
        lines += [f"**{law}** (envelope / published law)", "",
                  "| reading | slice | outcomes | best | " + " | ".join(map(resource_text, gap.at)) + " |",
                  "|---|---|---:|---:|" + "---:|" * len(gap.at)]
        for reading in gap.readings:
            sweep_dir = root / reading.slice
            if not (sweep_dir / layout.RESULTS).exists():
                lines.append(f"| {reading.label} | {reading.slice} | not run | |" + " |" * len(gap.at))
                continue
            for label, r, e in reading_outcomes(sweep_dir, law, reading):
                ratios = (gap_to_published(tuple(law.split("/")), r, e, np.asarray(gap.at, dtype=float)) if len(r)
                          else np.full(len(gap.at), math.nan))
                best = f"{e.min():.3g}" if len(e) else "-"
                lines.append(f"| {label} | {reading.slice} | {len(r):,} | {best} | "
                             + " | ".join(factor_text(x) for x in ratios) + " |")
        lines.append("")
    return "\n".join(lines)


def mechanism_factors(table: str) -> dict[str, dict[str, float]]:
    """law -> candidate -> largest factor, read from the summary table of ``benchmarks/mechanisms.py``'s output
    ("Which laws each candidate fits": a row per candidate, a cell 'yes (1.9x)' / 'no (15x)' / 'not run' per law)."""
    lines = table[table.index("**Which laws each candidate fits**"):].splitlines()
    header = next(line for line in lines if line.startswith("| candidate |"))
    laws = [cell.strip() for cell in header.strip("|").split("|")[1:-1]]
    factors: dict[str, dict[str, float]] = {law: {} for law in laws}
    for line in lines[lines.index(header) + 2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        name = cells[0].split(":")[0]
        for law, cell in zip(laws, cells[1:-1], strict=True):
            found = re.search(r"\(([\d.]+)x\)", cell)
            factors[law][name] = float(found.group(1)) if found else math.nan
    return factors


def resource_text(value: float) -> str:
    """300, 3000, 1e5, 2.5e9: a resource as the table writes it."""
    if value < 1e5:
        return f"{value:,.0f}"
    mantissa, exponent = f"{value:.1e}".split("e")
    return f"{mantissa.removesuffix('.0')}e{int(exponent)}"


def factor_text(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.2g}x"


def verdict(status: LawStatus, within: float) -> str:
    if status.slice is None:
        return f"not run: {status.why}"
    if math.isnan(status.largest):
        return "not run: the slice holds no outcome at these resources"
    return (f"within {within:g}x" if status.largest <= within else "not") + f" (largest {factor_text(status.largest)})"


def status_table(statuses: Sequence[LawStatus], within: float) -> str:
    """The Markdown table: one row per law."""
    lines = ["| published law | slice (date) | outcomes | envelope / law at three resources | half the tasks: "
             "envelope x | best candidate (its largest factor, where measured) | verdict | decided by |",
             "|---|---|---:|---|---|---|---|---|"]
    for status in statuses:
        best = status.best()
        factors = [f"{resource_text(r)}: {factor_text(x)}" for r, x in zip(status.at, status.factors, strict=False)]
        lines.append(" | ".join([
            f"| {status.law}", f"{status.slice} ({status.measured})" if status.slice else "-",
            f"{status.outcomes:,}" if status.slice else "-", ", ".join(factors) or "-",
            ", ".join(factor_text(x) for x in status.half_tasks) or "-",
            f"{best[0]} ({factor_text(best[1])}, {status.candidates_on})" if best else "-",
            verdict(status, within), status.decided_by or "-"]) + " |")
    return "\n".join(lines) + "\n"


def read_statuses(path: Path) -> dict[str, LawStatus]:
    """The committed entries by law (none where the file is not there)."""
    if not path.exists():
        return {}
    return {entry["law"]: LawStatus(**entry) for entry in json.loads(path.read_text())}


def statuses_json(statuses: Sequence[LawStatus]) -> str:
    return json.dumps([asdict(status) for status in statuses], indent=1, allow_nan=True) + "\n"


def with_table(document: str, table: str, begin: str = BEGIN, end: str = END) -> str:
    """``document`` with ``table`` between its markers ``begin`` and ``end`` (refused where it has none)."""
    if begin not in document or end not in document:
        raise ValueError(f"the document has no {begin} ... {end} markers")
    head, rest = document.split(begin, 1)
    return f"{head}{begin}\n{table}{end}{rest.split(end, 1)[1]}"


def figure_name(law: str) -> str:
    """The file name of a law's figure, as a report writes it (``analysis.figures.figure_stem``): PNG."""
    return law.replace("/", "__") + ".png"


def figures_block(statuses: Sequence[LawStatus], folder: str, present: Sequence[str]) -> str:
    """Markdown: one figure per law whose figure is among ``present`` (file names under ``folder``, relative to the
    document), titled with its slice and date, in the order of ``statuses``."""
    lines = []
    for status in statuses:
        name = figure_name(status.law)
        if name in present:
            lines += [f"**{status.law}** ({status.slice}, {status.measured})", "",
                      f"![{status.law}: outcomes, envelope, our law and the published one]({folder}/{name})", ""]
    return "\n".join(lines)


def table_in(document: str, begin: str = BEGIN, end: str = END) -> str:
    """The text between the markers ``begin`` and ``end`` of ``document`` (by default the status table's)."""
    return document.split(begin, 1)[1].split(end, 1)[0].removeprefix("\n")
