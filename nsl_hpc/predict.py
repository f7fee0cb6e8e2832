"""What it takes to reach a target error, from a sweep's fitted laws and their bootstrap intervals.

    python -m nsl_hpc.predict sweep_dir=runs/demo target=0.05 [metric=nmae] [resource=compute]
    python -m nsl_hpc.predict sweep_dir=runs/demo target=0.01 metric=nmse resource=data nsl.predict.decades=3

For every (system, arch): the resource its law needs to reach ``target`` (90% interval from the bootstrap
refits), "not reachable within the law" where the law stays above the target, how many decades beyond the
largest observed resource that is, and for compute the smallest model and data sizes among the outcomes on
the envelope near that compute (the mix that got there). Reads ``nsl_fits.parquet`` (``python -m
nsl_hpc.fit``) and ``results.parquet``.
"""

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.analysis.fitting import fits_path, read_results
from nsl_hpc.analysis.prediction import describe_need, what_it_takes
from nsl_hpc.analysis.settings import check_nsl, check_target
from nsl_hpc.atomic import read_parquet
from nsl_hpc.config import plain
from nsl_hpc.errors import ConfigError
from nsl_hpc.sweep.manifest import require_sweep


def main(cfg: DictConfig) -> int:
    nsl = plain(cfg.nsl)
    check_nsl(nsl)
    check_target(cfg.target, cfg.metric, cfg.resource, nsl)
    sweep_dir = require_sweep(cfg.sweep_dir)
    if not fits_path(sweep_dir).exists():
        raise ConfigError(f"{fits_path(sweep_dir)} does not exist; run python -m nsl_hpc.fit sweep_dir={sweep_dir}")
    fits = read_parquet(fits_path(sweep_dir)).to_pylist()
    entries = what_it_takes(read_results(sweep_dir), fits, cfg.resource, cfg.metric, lambda best: [cfg.target],
                            nsl)
    if not entries:
        raise ConfigError(f"no fitted {cfg.resource}-{cfg.metric} law in {fits_path(sweep_dir)}")
    symbol = nsl["resources"][cfg.resource]["symbol"]
    print(f"{nsl['metrics'][cfg.metric]} {cfg.target:g} by {cfg.resource} ({symbol}), "
          f"{nsl['bootstrap_level']:.0%} intervals from the bootstrap refits:")
    for entry in entries:
        print("  " + describe_need(entry, symbol))
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="predict")
