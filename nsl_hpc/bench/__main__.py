"""Training-speed benchmark: plain PyTorch loops against ours, side by side in one process.

    python -m nsl_hpc.bench [parts=[input_state,input_output,compiled]] [out=bench.json] [readme=docs/performance.md]

Prints (and with ``readme=`` writes between that file's markers of each part) the input-state part
(``nsl_hpc.bench.input_state``), the input-output part (``nsl_hpc.bench.input_output``) and compiled against
eager steps of both (``nsl_hpc.bench.compiled``). Everything runs on one thread. ``out=`` writes the headline
figures as JSON.
"""

import json
import tempfile
from pathlib import Path

import torch
from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.bench.compiled import compiled_part
from nsl_hpc.bench.input_output import input_output_part
from nsl_hpc.bench.input_state import input_state_part
from nsl_hpc.bench.settings import bench_settings
from nsl_hpc.core.atomic import write_text

MARKERS = {"input_state": ("<!-- bench:start -->", "<!-- bench:end -->"),
           "input_output": ("<!-- bench-io:start -->", "<!-- bench-io:end -->"),
           "compiled": ("<!-- bench-compiled:start -->", "<!-- bench-compiled:end -->")}


def write_readme(path: Path, table: str, part: str) -> None:
    """Replace the block between ``part``'s markers of ``path`` with ``table``."""
    start, end = MARKERS[part]
    text = path.read_text()
    if start not in text or end not in text:
        raise ValueError(f"{path} lacks the markers {start} ... {end}")
    head, rest = text.split(start, 1)
    write_text(f"{head}{start}\n{table}\n{end}{rest.split(end, 1)[1]}", path)


PARTS = {"input_state": input_state_part, "input_output": input_output_part, "compiled": compiled_part}


def main(cfg: DictConfig) -> int:
    settings = bench_settings(cfg)
    torch.set_num_threads(1)
    headline = {}
    with tempfile.TemporaryDirectory() as folder:
        for part in settings.parts:
            table, figures = PARTS[part](settings, Path(folder))
            print(table, end="\n\n")
            if settings.readme:
                write_readme(Path(settings.readme), table, part)
            headline.update(figures)
    if settings.out:
        write_text(json.dumps(headline, indent=2), Path(settings.out))
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="bench")
