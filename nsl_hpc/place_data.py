"""Put the measured benchmark files where the input-output tasks read them (``data_dir``, the layout of the
``nonlinear_benchmarks`` loaders): copied from a folder that holds them, else downloaded by the benchmark's loader.

    python -m nsl_hpc.place_data source=../shared/data
    python -m nsl_hpc.place_data data_dir=/scratch/nsl/data 'systems=[silverbox]'     # downloaded where it can be

For each measured system (conf/system/<name>.yaml, ``source.files``): files already in ``data_dir`` are kept; the
others are found by name anywhere under ``source`` and copied (a ``.zip`` the loader only checks for, Silverbox's
archive whose contents are the .mat files, is written as an empty archive); what no folder holds is downloaded by
its ``nonlinear_benchmarks`` loader (``download``). A system that is neither is one line saying where its files are
published (``pages``); what was placed before it stays.
"""

import contextlib
import io
import shutil
import socket
import zipfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from nsl_hpc import cli
from nsl_hpc.config import config_dir
from nsl_hpc.core.atomic import replacing
from nsl_hpc.core.errors import ConfigError, one_line


def find_file(source: Path | None, name: str) -> Path | None:
    """The one file called ``name`` under ``source`` (the shallowest when there are several; None: none, or no
    source)."""
    if source is None:
        return None
    found = sorted(source.rglob(name), key=lambda path: len(path.parts))
    return found[0] if found else None


def copy_in(origin: Path | None, target: Path) -> str:
    """``target`` from ``origin`` (an empty archive for a ``.zip`` the loader only checks for); what was done."""
    with replacing(target) as temporary:
        if target.suffix == ".zip":
            zipfile.ZipFile(temporary, "w").close()
            return f"marker  {target}"
        assert origin is not None
        shutil.copyfile(origin, temporary)
    return f"copied  {target} <- {origin}"


def download(name: str, loader: str, data_dir: Path, timeout_s: float, page: str) -> str:
    """The benchmark's files fetched into ``data_dir`` by ``nonlinear_benchmarks.<loader>``, or a one-line
    ConfigError saying where they are published."""
    import nonlinear_benchmarks

    data_dir.mkdir(parents=True, exist_ok=True)
    before = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout_s)  # the loaders open connections without a timeout of their own
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            getattr(nonlinear_benchmarks, loader)(dir_placement=str(data_dir))
    except Exception as error:
        raise ConfigError(f"{name}: its files are in no source folder and the download by nonlinear_benchmarks."
                          f"{loader} failed ({type(error).__name__}: {one_line(str(error))[:120]}); get them from "
                          f"{page} and run again with source=<their folder> (make data DATA_SOURCE=<their folder>)"
                          ) from None
    finally:
        socket.setdefaulttimeout(before)
    return f"downloaded {name} into {data_dir} (nonlinear_benchmarks.{loader})"


def place_system(name: str, files: list[str], loader: str | None, source: Path | None, data_dir: Path,
                 cfg: DictConfig) -> list[str]:
    """Place one system's ``files`` (relative to ``data_dir``); returns what was done, a line each."""
    missing = [relative for relative in files if not (data_dir / relative).is_file()]
    found = {relative: find_file(source, Path(relative).name) for relative in missing}
    if all(origin is not None or relative.endswith(".zip") for relative, origin in found.items()):
        return ([f"kept    {data_dir / relative}" for relative in files if relative not in missing]
                + [copy_in(found[relative], data_dir / relative) for relative in missing])
    absent = next(relative for relative, origin in found.items() if origin is None and not relative.endswith(".zip"))
    page = cfg.pages.get(name, "the benchmark's page")
    where = f"under source={str(source)!r}" if source is not None else "in data_dir, and no source folder is given"
    if loader is None or not cfg.download:
        how = "it has no nonlinear_benchmarks loader" if loader is None else "download=false"
        raise ConfigError(f"{name}: no file named {Path(absent).name} {where}, and it is not downloaded ({how}); get "
                          f"it from {page} and run again with source=<its folder>")
    line = download(name, loader, data_dir, cfg.download_timeout_s, page)
    still = [relative for relative in files if not (data_dir / relative).is_file()]
    if still:
        raise ConfigError(f"{name}: nonlinear_benchmarks.{loader} left no {data_dir / still[0]}; get the files from "
                          f"{page} and run again with source=<their folder>")
    return [line]


def main(cfg: DictConfig) -> int:
    source = None if cfg.source is None else Path(cfg.source)
    if source is not None and not source.is_dir():
        raise ConfigError(f"source={cfg.source!r} is not a directory (null: no folder; what data_dir lacks is "
                          "downloaded)")
    data_dir = Path(cfg.data_dir)
    for name in cfg.systems:
        system = OmegaConf.load(config_dir() / "system" / f"{name}.yaml").source
        for line in place_system(name, list(system.files), system.get("loader"), source, data_dir, cfg):
            print(line)
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="place_data")
