"""The status table of docs/reproduction.md: every published law against the slice of `make repro` that measures it
(conf/reproduction.yaml). Reads the merged slices under ``root`` into the committed ``status`` file (a slice not on
this machine keeps its entry and date), then writes the table from that file alone between the document's status
markers, and prints it; the candidates' table, the gap slices' table (what decides each remaining gap), each slice's
fits beside the published laws (its report's ``comparison.md``) and each law's figure (its report's) are written
beside it, the figures shown in the document between its law-figure markers. ``train=true`` first trains each
slice's candidates and each gap slice that is not there.

    python benchmarks/reproduction_status.py [root=runs/repro] [collect=false] [train=true]
"""

import subprocess
import sys
from pathlib import Path

from nsl_hpc.analysis.reproduction import (
    FIGURES_BEGIN,
    FIGURES_END,
    LawGap,
    LawSlice,
    candidates_table,
    collect,
    figure_name,
    figures_block,
    gaps_table,
    mechanism_factors,
    read_statuses,
    status_table,
    statuses_json,
    with_table,
)
from nsl_hpc.config import plain, tool_settings
from nsl_hpc.config.schema import typed
from nsl_hpc.core.atomic import replacing, write_text
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep import layout


def copy_file(source: Path, target: Path) -> None:
    """``source``'s bytes to ``target``, atomically."""
    with replacing(target) as temporary:
        temporary.write_bytes(source.read_bytes())


def to_train(cfg: dict) -> list[tuple[str, str, list[str]]]:
    """(sweep directory name under ``root``, sweep preset, overrides) of every candidate of ``cfg["candidates"]``
    (``<slice>__<name>``) and every slice of ``cfg["gap_slices"]``."""
    runs = [(f"{slice_name}__{name}", cfg["sweeps"][slice_name], list(overrides))
            for slice_name, candidates in cfg["candidates"].items() for name, overrides in candidates.items()]
    return runs + [(name, spec["sweep"], list(spec["overrides"])) for name, spec in cfg["gap_slices"].items()]


def train_missing(cfg: dict) -> None:
    """Launch and merge each sweep of ``to_train`` not yet merged under ``root`` (a launch that is there goes on
    from where it stopped)."""
    for name, sweep, overrides in to_train(cfg):
        sweep_dir = Path(cfg["root"]) / name
        if (sweep_dir / layout.RESULTS).exists():
            continue
        print(f"== {name}: {sweep_dir}", flush=True)
        launch = ["nsl_hpc.launch", f"+sweep={sweep}", f"sweep_dir={sweep_dir}", f"launcher.workers={cfg['workers']}",
                  *overrides]
        for command in (launch, ["nsl_hpc.merge", f"sweep_dir={sweep_dir}"]):
            if subprocess.run([sys.executable, "-m", *command]).returncode != 0:  # it printed why
                sys.exit(f"error: {command[0]} of {name} failed; the sweeps before it are kept, and running this "
                         "again goes on from there")


def main() -> None:
    if {"-h", "--help"} & set(sys.argv[1:]):
        sys.exit(print(__doc__) or 0)
    cfg = plain(tool_settings("reproduction", sys.argv[1:]))
    status_path, document = Path(cfg["status"]), Path(cfg["document"])
    try:
        laws = {law: typed(LawSlice, spec, f"laws.{law}") for law, spec in cfg["laws"].items()}
        gaps = {law: typed(LawGap, spec, f"gaps.{law}") for law, spec in cfg["gaps"].items()}
    except ConfigError as error:
        sys.exit(f"error: {error}")
    before = read_statuses(status_path)
    if cfg["train"]:
        train_missing(cfg)
    if cfg["collect"]:
        mechanisms = mechanism_factors(Path(cfg["mechanisms"]).read_text())
        statuses = collect(laws, Path(cfg["root"]), cfg["candidates"], mechanisms, before, cfg["halves"])
        write_text(statuses_json(statuses), status_path)
        if any((Path(cfg["root"]) / slice_name).exists() for slice_name in cfg["candidates"]):
            output = Path(cfg["candidates_output"])
            write_text(candidates_table(laws, Path(cfg["root"]), cfg["candidates"], cfg["learned_below"],
                                        output.read_text() if output.exists() else ""), output)
        if any((Path(cfg["root"]) / reading.slice).exists() for gap in gaps.values() for reading in gap.readings):
            write_text(gaps_table(gaps, Path(cfg["root"])), Path(cfg["gaps_output"]))
        for slice_name in cfg["sweeps"]:  # each slice's fits beside the published laws, as its report wrote them
            comparison = Path(cfg["root"]) / slice_name / "comparison.md"
            if comparison.exists():
                copy_file(comparison, Path(cfg["comparisons"]) / f"comparison__{slice_name}.md")
        for law, spec in laws.items():  # each law's figure, as its slice's report drew it
            drawn = Path(cfg["root"]) / str(spec.slice) / layout.FIGURES / "nsl" / figure_name(law)
            if spec.slice and drawn.exists():
                copy_file(drawn, Path(cfg["comparisons"]) / figure_name(law))
    else:
        statuses = [before[law] for law in cfg["laws"]]
    table = status_table(statuses, cfg["within"])
    folder = Path(cfg["comparisons"])
    present = [path.name for path in folder.glob("*.png")]
    text = with_table(document.read_text(), table)
    text = with_table(text, figures_block(statuses, folder.relative_to(document.parent).as_posix(), present),
                      FIGURES_BEGIN, FIGURES_END)
    write_text(text, document)
    print(table)


if __name__ == "__main__":
    main()
