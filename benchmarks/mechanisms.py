"""The mechanism table (docs/reproduction.md, "One table for every candidate"): every candidate of
conf/mechanisms.yaml trains the same slices (one local launch and merge per candidate and part, into
<root>/<candidate>/<part>; a finished sweep is not trained again), and every candidate is scored on every
published law the slices cover: our step envelope over the law at the resources of ``at``, the least resource
at which the envelope is below ``below``, and whether the envelope lies within ``within`` of the law at all of
them. Prints the tables and writes them to <root>/table.md.

    python benchmarks/mechanisms.py [root=runs/mechanisms] [workers=2] [only=[baseline,repeat_8]] [train=false]

``train=false`` tabulates the sweeps that are there without launching anything.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from omegaconf import DictConfig

from nsl_hpc.analysis.published import gap_to_published, resource_columns
from nsl_hpc.config import tool_settings
from nsl_hpc.core.atomic import write_text


def settings(argv: list[str]) -> DictConfig:
    """conf/mechanisms.yaml with ``key=value`` overrides (a key it does not have is refused)."""
    return tool_settings("mechanisms", argv)


def chosen(cfg: DictConfig) -> list[DictConfig]:
    names = [candidate.name for candidate in cfg.candidates]
    unknown = sorted(set(cfg.only or []) - set(names))
    if unknown:
        sys.exit(f"error: only={list(cfg.only)}: no candidate {', '.join(unknown)}; conf/mechanisms.yaml has: "
                 f"{', '.join(names)}")
    return [candidate for candidate in cfg.candidates if not cfg.only or candidate.name in cfg.only]


def parts_of(candidate: DictConfig, cfg: DictConfig) -> list[str]:
    return list(candidate.get("parts") or cfg.parts.keys())


def train(candidate: DictConfig, part: str, cfg: DictConfig) -> None:
    """Launch the candidate's sweep of ``part`` on local workers (resuming one that is there), then merge it."""
    sweep_dir = Path(cfg.root) / candidate.name / part
    print(f"== {candidate.name} / {part}: {sweep_dir}", flush=True)
    for command in (["nsl_hpc.launch", f"+sweep={cfg.parts[part].sweep}", f"sweep_dir={sweep_dir}",
                     f"launcher.workers={cfg.workers}", *candidate.overrides],
                    ["nsl_hpc.merge", f"sweep_dir={sweep_dir}"]):
        if subprocess.run([sys.executable, "-m", *command]).returncode != 0:  # it printed why
            sys.exit(f"error: {command[0]} of {candidate.name} / {part} failed; the sweeps before it are kept, and "
                     "running this again goes on from there")


def outcomes(sweep_dir: Path, system: str, arch: str) -> list[dict]:
    """The finished rows of (system, arch) in a merged sweep."""
    rows = pq.read_table(sweep_dir / "results.parquet").to_pylist()
    return [row for row in rows if row["system"] == system and row["arch"] == arch and row["status"] == "ok"]


def law_table(law: str, cfg: DictConfig, candidates: list[DictConfig]) -> tuple[list[str], dict[str, float]]:
    """The markdown lines of one law's table and, per candidate with outcomes, the largest factor between its
    envelope and the law (either way) over the resources of ``at``."""
    system, arch, resource, metric = key = tuple(law.split("/"))
    part = next(name for name, entry in cfg.parts.items() if law in entry.laws)
    at = np.asarray(cfg.at[law], dtype=float)
    lines = [f"**{law}** (envelope / published law; {metric} scores)", "",
             "| candidate | outcomes | " + " | ".join(map(short, at)) + f" | first below {cfg.below:g} "
             f"| within {cfg.within:g}x (largest factor) |", "|---|---:|" + "---:|" * (len(at) + 2)]
    worst: dict[str, float] = {}
    for candidate in candidates:
        borrowed = part in (candidate.get("baseline_parts") or [])
        sweep_dir = Path(cfg.root) / ("baseline" if borrowed else candidate.name) / part
        label = f"{candidate.name} (the baseline's runs: its change leaves them)" if borrowed else candidate.name
        if not (sweep_dir / "results.parquet").exists():
            lines.append(f"| {label} | not run | " + " | ".join("" for _ in at) + " | | |")
            continue
        rows = outcomes(sweep_dir, system, arch)
        column = candidate.get("resource_column") if resource == "compute" else None
        r = np.array([row[column or resource_columns()[resource]] for row in rows], dtype=float)
        e = np.array([row[metric] for row in rows], dtype=float)
        ratios = gap_to_published(key, r, e, at)
        known = ratios[~np.isnan(ratios)]
        worst[candidate.name] = float(np.max(np.maximum(known, 1 / known))) if len(known) else np.nan
        below = r[e < cfg.below]
        first = short(below.min()) if len(below) else f"> {short(r.max())}"
        cells = " | ".join("-" if np.isnan(x) else f"{x:.2f}" for x in ratios)
        lines.append(f"| {label} | {len(rows)} | {cells} | {first} | {verdict(worst[candidate.name], cfg)} |")
    return lines, worst


def short(resource: float) -> str:
    """150, 1170, 3e4, 2.2e6: a resource as the tables write it."""
    if resource < 1e4:
        return f"{resource:.0f}"
    mantissa, exponent = f"{resource:.1e}".split("e")
    return f"{mantissa.removesuffix('.0')}e{int(exponent)}"


def verdict(worst: float, cfg: DictConfig) -> str:
    """'yes' where the largest factor between envelope and law is within ``cfg.within``; the factor beside."""
    if np.isnan(worst):
        return "not run"
    return f"{'yes' if worst <= cfg.within else 'no'} ({worst:.2g}x)"


def tables(cfg: DictConfig, candidates: list[DictConfig]) -> str:
    laws = [law for part in cfg.parts.values() for law in part.laws]
    lines: list[str] = []
    verdicts = {}
    for law in laws:
        law_lines, verdicts[law] = law_table(law, cfg, candidates)
        lines += [*law_lines, ""]
    lines += [f"**Which laws each candidate fits** (within {cfg.within:g}x at every resource of its table; in "
              "brackets the largest factor between envelope and law, either way)", "",
              "| candidate | " + " | ".join(laws) + " | all |", "|---|" + "---|" * (len(laws) + 1)]
    for candidate in candidates:
        cells = [verdict(verdicts[law].get(candidate.name, np.nan), cfg) for law in laws]
        lines.append(f"| {candidate.name}: {candidate.label} | " + " | ".join(cells)
                     + f" | {'yes' if all(cell.startswith('yes') for cell in cells) else 'no'} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    cfg = settings(sys.argv[1:])
    candidates = chosen(cfg)
    if cfg.train:
        for part in cfg.parts:  # every candidate's first part before any second part: the cheap answers first
            for candidate in candidates:
                if part in parts_of(candidate, cfg):
                    train(candidate, part, cfg)
    text = tables(cfg, candidates)
    print(text)
    Path(cfg.root).mkdir(parents=True, exist_ok=True)
    write_text(text, Path(cfg.root) / "table.md")


if __name__ == "__main__":
    main()
