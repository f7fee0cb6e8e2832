"""Where a reproduction stands against every published law: one entry per law (``LawStatus``), collected from the
merged sweeps of its slice, and the Markdown status table written from those entries alone, so that the table in the
docs can be regenerated from the committed numbers (``benchmarks/reproduction_status.py``)."""

import datetime
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from nsl_hpc.analysis.fitting import pair_outcomes
from nsl_hpc.analysis.learning import MEAN_PREDICTOR, learned
from nsl_hpc.analysis.published import gap_to_published, resource_columns
from nsl_hpc.config.schema import setting

BEGIN, END = "<!-- status table: begin -->", "<!-- status table: end -->"


@dataclass(frozen=True)
class LawSlice:
    """A published law's entry of conf/reproduction.yaml's ``laws``: the slice that measures it and the resources
    its factors are taken at; a law no slice covers says why."""

    at: list[float] = setting("the resources at which our envelope is set over the law", 0, low_open=True,
                              nonempty=True)
    slice: str | None = setting("the slice that measures it (<root>/<slice>; null: none)", default=None)
    why: str = setting("why no slice measures it", default="its slice was not run")


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

    def best(self) -> tuple[str, float] | None:
        """The candidate whose largest factor is smallest, None without candidates."""
        known = {name: value for name, value in self.candidates.items() if not math.isnan(value)}
        return min(known.items(), key=lambda item: item[1]) if known else None


def largest_factor(ratios: np.ndarray) -> float:
    """The largest factor between envelope and law, either way, over the resources that have an envelope."""
    known = ratios[~np.isnan(ratios)]
    return float(np.max(np.maximum(known, 1 / known))) if len(known) else math.nan


def envelope_factors(sweep_dir: Path, law: str, at: Sequence[float], column: str | None = None
                     ) -> tuple[int, np.ndarray]:
    """(outcomes, envelope / law at ``at``) of one law on a merged sweep (its finished rows of the law's pair), the
    envelope of the results ``column`` (None: the law's metric)."""
    system, arch, resource, metric = key = tuple(law.split("/"))
    metric = column or metric
    table = pq.read_table(sweep_dir / "results.parquet")
    rows = [row for row in table.to_pylist() if (row["system"], row["arch"], row["status"]) == (system, arch, "ok")]
    r = np.array([row[resource_columns()[resource]] for row in rows], dtype=float)
    e = np.array([row[metric] for row in rows], dtype=float)
    keep = np.isfinite(e) & (e > 0)
    return int(keep.sum()), gap_to_published(key, r[keep], e[keep], np.asarray(at, dtype=float))


def collect(laws: Mapping[str, LawSlice], root: Path, candidates: Mapping[str, Mapping[str, str]],
            mechanism_factors: Mapping[str, dict[str, float]], before: Mapping[str, LawStatus]) -> list[LawStatus]:
    """Each law's status from ``root``/<slice> (and ``root``/<slice>__<candidate> for the slice's ``candidates``;
    ``mechanism_factors``: law -> candidate -> largest factor, from the mechanism table); a law whose slice is not
    under ``root`` keeps its entry of ``before``, or is not run, with its config's ``why``."""
    today = datetime.date.today().isoformat()
    statuses = []
    for law, spec in laws.items():
        at = [float(value) for value in spec.at]
        if not spec.slice or not (root / spec.slice / "results.parquet").exists():
            statuses.append(before.get(law) or LawStatus(law, at, why=spec.why))
            continue
        sweep_dir = root / spec.slice
        outcomes, ratios = envelope_factors(sweep_dir, law, at)
        scored, where = dict(mechanism_factors.get(law, {})), "make mechanisms" if law in mechanism_factors else ""
        for name in candidates.get(spec.slice, {}):
            other = root / f"{spec.slice}__{name}"
            if (other / "results.parquet").exists():
                scored[name], where = largest_factor(envelope_factors(other, law, at)[1]), spec.slice
        statuses.append(LawStatus(law, at, spec.slice, today, outcomes, [float(x) for x in ratios],
                                  largest_factor(ratios), scored, where))
    return statuses


def candidates_table(laws: Mapping[str, LawSlice], root: Path, candidates: Mapping[str, Mapping[str, Sequence[str]]],
                     below: float) -> str:
    """Per slice with candidates, a Markdown table of its default run and each candidate run under ``root``: the
    overrides, the outcomes, how many learned (nMAE below ``below`` times the mean predictor's) and, per law of the
    slice, the envelope over the law at its resources and the largest factor ('' where no slice has candidates)."""
    lines: list[str] = []
    for slice_name, runs in candidates.items():
        slice_laws = [law for law, spec in laws.items() if spec.slice == slice_name]
        for law in slice_laws:
            at = [float(value) for value in laws[law].at]
            lines += [f"**{law}** on `{slice_name}` (envelope / published law)", "",
                      "| settings | outcomes | learned | " + " | ".join(map(resource_text, at))
                      + " | largest factor |", "|---|---:|---:|" + "---:|" * (len(at) + 1)]
            for name, overrides in {"default": [], **runs}.items():
                sweep_dir = root / (slice_name if name == "default" else f"{slice_name}__{name}")
                label = f"{name}" + (f" (`{' '.join(overrides)}`)" if overrides else "")
                if not (sweep_dir / "results.parquet").exists():
                    lines.append(f"| {label} | not run | | " + " | ".join("" for _ in at) + " | |")
                    continue
                pair = pair_outcomes(pq.read_table(sweep_dir / "results.parquet"), *law.split("/")[:2])
                ratios = envelope_factors(sweep_dir, law, at)[1]
                scored = MEAN_PREDICTOR in pair.column_names and pair[MEAN_PREDICTOR].null_count == 0
                cells = [f"{int(learned(pair, below).sum()):,}" if scored else "- (no mean predictor's score)",
                         *(factor_text(x) for x in ratios), factor_text(largest_factor(ratios))]
                lines.append(f"| {label} | {pair.num_rows:,} | " + " | ".join(cells) + " |")
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
    lines = ["| published law | slice (date) | outcomes | envelope / law at three resources | best candidate "
             "(its largest factor, where measured) | verdict |", "|---|---|---:|---|---|---|"]
    for status in statuses:
        best = status.best()
        factors = [f"{resource_text(r)}: {factor_text(x)}" for r, x in zip(status.at, status.factors, strict=False)]
        lines.append(" | ".join([
            f"| {status.law}", f"{status.slice} ({status.measured})" if status.slice else "-",
            f"{status.outcomes:,}" if status.slice else "-", ", ".join(factors) or "-",
            f"{best[0]} ({factor_text(best[1])}, {status.candidates_on})" if best else "-",
            verdict(status, within)]) + " |")
    return "\n".join(lines) + "\n"


def read_statuses(path: Path) -> dict[str, LawStatus]:
    """The committed entries by law (none where the file is not there)."""
    if not path.exists():
        return {}
    return {entry["law"]: LawStatus(**entry) for entry in json.loads(path.read_text())}


def statuses_json(statuses: Sequence[LawStatus]) -> str:
    return json.dumps([asdict(status) for status in statuses], indent=1, allow_nan=True) + "\n"


def with_table(document: str, table: str) -> str:
    """``document`` with ``table`` between its status markers (refused where it has none)."""
    if BEGIN not in document or END not in document:
        raise ValueError(f"the document has no {BEGIN} ... {END} markers")
    head, rest = document.split(BEGIN, 1)
    return f"{head}{BEGIN}\n{table}{END}{rest.split(END, 1)[1]}"


def table_in(document: str) -> str:
    """The table between the status markers of ``document``."""
    return document.split(BEGIN, 1)[1].split(END, 1)[0].removeprefix("\n")
