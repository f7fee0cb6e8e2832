"""How far apart the standard scores of one input-output model are: prints, for a few trained models on the
stand-ins and on the measured benchmarks, the nMAE of every test record in free run and (NARX) one step ahead,
beside the error floors (alpha) of the paper's published input-output laws; asserts nothing.

    python benchmarks/io_scores.py [--data-dir data] [--workers 2]

Each line is one real task (``nsl_hpc.sweep.task.run_task``, the study's training config) at a small grid point
that trains in about a minute on one core.
"""

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from omegaconf import OmegaConf

from nsl_hpc.config import compose_config
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.task import run_task

POINTS = {"narx": {"iter_multiplier": 4, "width_tier": 16, "depth": 1},
          "subnet": {"iter_multiplier": 1, "width_tier": 8, "depth": 1}}
CASES = [(system, arch, tier) for system, tier in (("silverbox_sim", 2000), ("wiener_hammerstein_sim", 2500),
                                                   ("silverbox", 2000), ("wiener_hammerstein", 2500))
         for arch in ("narx", "subnet")]


def published_floors() -> dict[tuple[str, str], list[float]]:
    """alpha of each published input-output law (nMAE), by (system, arch)."""
    floors: dict[tuple[str, str], list[float]] = {}
    for law in OmegaConf.load(Path(__file__).parents[1] / "conf" / "published_laws.yaml").laws:
        if law.system in ("silverbox", "wiener_hammerstein"):
            floors.setdefault((law.system, law.arch), []).append(float(law.alpha))
    return floors


def run_case(system: str, arch: str, tier: int, data_dir: str, root: str) -> str:
    overrides = ["study=input_output", f"system={system}", f"arch={arch}", f"out_dir={root}/{system}-{arch}",
                 f"cache_dir={root}/cache", f"data_dir={data_dir}", f"data_tier={tier}", "seed=0",
                 *(f"{key}={value}" for key, value in POINTS[arch].items())]
    try:
        row = run_task(compose_config(overrides, "one_task")).row
    except ConfigError as error:
        return f"{system:22s} {arch:6s} skipped: {error}"
    scores = {name.removeprefix("nmae_"): value for name, value in row.items()
              if name.startswith("nmae_") and value is not None}
    default = row["nmae"]
    cells = "  ".join(f"{name} {value:.4f} ({value / default:.2g}x)" for name, value in scores.items())
    floors = published_floors().get((system, arch))
    return (f"{system:22s} {arch:6s} n_l {row['train_points']:,} n_i {row['steps']:,} n_h {row['width']}: "
            f"{cells}{f'  published alpha {floors}' if floors else ''}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-dir", default="data", help="the measured systems' data_dir")
    parser.add_argument("--workers", type=int, default=2, help="tasks run at once (one core each)")
    args = parser.parse_args()
    print("nMAE of each <mode>_<record> (x the row's default, the free run on system.score_on)")
    with tempfile.TemporaryDirectory() as root, ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(run_case, *case, str(Path(args.data_dir).resolve()), root) for case in CASES]
        for future in futures:
            print(future.result(), flush=True)


if __name__ == "__main__":
    main()
