"""The status table of docs/reproduction.md: every published law against the slice of `make repro` that measures it
(conf/reproduction.yaml). Reads the merged slices under ``root`` into the committed ``status`` file (a slice not on
this machine keeps its entry and date), then writes the table from that file alone between the document's status
markers, and prints it; the candidates' table and each slice's fits beside the published laws (its report's
``comparison.md``) are copied beside it. ``train=true`` first trains each slice's candidates that are not there.

    python benchmarks/reproduction_status.py [root=runs/repro] [collect=false] [train=true]
"""

import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

from nsl_hpc.analysis.reproduction import (
    LawSlice,
    candidates_table,
    collect,
    mechanism_factors,
    read_statuses,
    status_table,
    statuses_json,
    with_table,
)
from nsl_hpc.atomic import write_text
from nsl_hpc.config import config_dir, plain
from nsl_hpc.config.schema import typed
from nsl_hpc.errors import ConfigError


def train_candidates(cfg: dict) -> None:
    """Launch and merge each candidate sweep of ``cfg["candidates"]`` not yet merged under ``root`` (a launch that
    is there goes on from where it stopped)."""
    for slice_name, candidates in cfg["candidates"].items():
        for name, overrides in candidates.items():
            sweep_dir = Path(cfg["root"]) / f"{slice_name}__{name}"
            if (sweep_dir / "results.parquet").exists():
                continue
            print(f"== {slice_name} / {name}: {sweep_dir}", flush=True)
            for command in (["nsl_hpc.launch", f"+sweep={cfg['sweeps'][slice_name]}", f"sweep_dir={sweep_dir}",
                             f"launcher.workers={cfg['workers']}", *overrides],
                            ["nsl_hpc.merge", f"sweep_dir={sweep_dir}"]):
                if subprocess.run([sys.executable, "-m", *command]).returncode != 0:  # it printed why
                    sys.exit(f"error: {command[0]} of {slice_name} / {name} failed; the sweeps before it are kept, "
                             "and running this again goes on from there")


def main() -> None:
    if {"-h", "--help"} & set(sys.argv[1:]):
        sys.exit(print(__doc__) or 0)
    cfg = OmegaConf.load(config_dir() / "reproduction.yaml")
    OmegaConf.set_struct(cfg, True)
    try:
        cfg = plain(OmegaConf.merge(cfg, OmegaConf.from_dotlist(sys.argv[1:])))
    except Exception as error:  # OmegaConf's errors name the key; one line, no traceback
        sys.exit(f"error: {str(error).splitlines()[0]}")
    status_path, document = Path(cfg["status"]), Path(cfg["document"])
    try:
        laws = {law: typed(LawSlice, spec, f"laws.{law}") for law, spec in cfg["laws"].items()}
    except ConfigError as error:
        sys.exit(f"error: {error}")
    before = read_statuses(status_path)
    if cfg["train"]:
        train_candidates(cfg)
    if cfg["collect"]:
        mechanisms = mechanism_factors(Path(cfg["mechanisms"]).read_text())
        statuses = collect(laws, Path(cfg["root"]), cfg["candidates"], mechanisms, before)
        write_text(statuses_json(statuses), status_path)
        if any((Path(cfg["root"]) / slice_name).exists() for slice_name in cfg["candidates"]):
            write_text(candidates_table(laws, Path(cfg["root"]), cfg["candidates"], cfg["learned_below"]),
                       Path(cfg["candidates_output"]))
        for slice_name in cfg["sweeps"]:  # each slice's fits beside the published laws, as its report wrote them
            comparison = Path(cfg["root"]) / slice_name / "comparison.md"
            if comparison.exists():
                write_text(comparison.read_text(), Path(cfg["comparisons"]) / f"comparison__{slice_name}.md")
    else:
        statuses = [before[law] for law in cfg["laws"]]
    table = status_table(statuses, cfg["within"])
    write_text(with_table(document.read_text(), table), document)
    print(table)


if __name__ == "__main__":
    main()
