"""Copy measured benchmark files into the layout the ``nonlinear_benchmarks`` loaders read offline.

    python -m nsl_hpc.place_data source=../shared/data
    python -m nsl_hpc.place_data source=~/downloads data_dir=/scratch/nsl/data 'systems=[silverbox]'

For each measured system (conf/system/<name>.yaml, ``source.files``) the files are found by name anywhere
under ``source`` and copied to ``data_dir/<file>``; a ``.zip`` the loader only checks for (Silverbox's
archive, whose contents are the .mat files) is written as an empty archive. Files already in place are
left alone. Nothing is downloaded.
"""

import shutil
import zipfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from nsl_hpc import cli
from nsl_hpc.atomic import replacing
from nsl_hpc.config import config_dir
from nsl_hpc.errors import ConfigError


def find_file(source: Path, name: str) -> Path:
    """The one file called ``name`` under ``source`` (the shallowest when there are several)."""
    found = sorted(source.rglob(name), key=lambda path: len(path.parts))
    if not found:
        raise ConfigError(f"no file named {name} under source={str(source)!r}")
    return found[0]


def place(source: Path, data_dir: Path, relative: str) -> str:
    """Put ``data_dir/relative`` in place from ``source``; returns what was done."""
    target = data_dir / relative
    if target.is_file():
        return f"kept    {target}"
    with replacing(target) as temporary:
        if target.suffix == ".zip":
            zipfile.ZipFile(temporary, "w").close()
            return f"marker  {target}"
        origin = find_file(source, target.name)
        shutil.copyfile(origin, temporary)
    return f"copied  {target} <- {origin}"


def main(cfg: DictConfig) -> int:
    source, data_dir = Path(cfg.source), Path(cfg.data_dir)
    if not source.is_dir():
        raise ConfigError(f"source={cfg.source!r} is not a directory")
    plans = [(name, OmegaConf.load(config_dir() / "system" / f"{name}.yaml").source.files)
             for name in cfg.systems]
    for _, files in plans:  # every file found before anything is written
        for relative in files:
            if not relative.endswith(".zip"):
                find_file(source, Path(relative).name)
    for _, files in plans:
        for relative in files:
            print(place(source, data_dir, relative))
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="place_data")
