"""What it takes to reach a target error, from a sweep's fitted laws and their bootstrap intervals.

    python -m nsl_hpc.predict sweep_dir=runs/demo target=0.05 [metric=nmae] [resource=compute]
    python -m nsl_hpc.predict sweep_dir=runs/demo target=0.01 metric=nmse resource=data nsl.predict.decades=3

For every (system, arch): the resource its law needs to reach ``target`` (90% interval from the bootstrap
refits), "not reachable within the law" where the law stays above the target, how many decades beyond the
largest observed resource that is, and for compute the smallest model and data sizes among the outcomes on
the envelope near that compute (the mix that got there). Reads ``nsl_fits.parquet`` (``python -m
nsl_hpc.fit``) and ``results.parquet``.

Then, for every (system, arch), the configuration (the study's size axes: epochs, data tier, width and depth
tiers) that reaches ``target`` at the least cost by a joint law of the error over model size, data and training
length (nsl_hpc.analysis.joint_law, settings ``nsl.joint``), among the sweep's values of each axis and two
doublings beyond; its core-hours on this cluster (the planner's cost model times the sweep's measured over
predicted core-hours) with an interval from refits on resampled configurations; and a backtest: the law fitted on
the cheaper configurations, predicting the best outcome of the dearer ones and what reaching it costs.
"""

from pathlib import Path

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.analysis.cheapest import calibration_of, cheapest_configurations, describe_cheapest
from nsl_hpc.analysis.fitting import fits_path, read_results
from nsl_hpc.analysis.nsl_settings import Nsl, check_target, nsl_settings
from nsl_hpc.analysis.prediction import describe_need, what_it_takes
from nsl_hpc.core.atomic import read_parquet
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, require_sweep


def main(cfg: DictConfig) -> int:
    nsl = nsl_settings(cfg.nsl)
    check_target(cfg.target, cfg.metric, cfg.resource, nsl)
    sweep_dir = require_sweep(cfg.sweep_dir)
    if not fits_path(sweep_dir).exists():
        raise ConfigError(f"{fits_path(sweep_dir)} does not exist; run python -m nsl_hpc.fit sweep_dir={sweep_dir}")
    fits = read_parquet(fits_path(sweep_dir)).to_pylist()
    entries = what_it_takes(read_results(sweep_dir), fits, cfg.resource, cfg.metric, lambda best: [cfg.target],
                            nsl)
    if not entries:
        raise ConfigError(f"no fitted {cfg.resource}-{cfg.metric} law in {fits_path(sweep_dir)}")
    symbol = nsl.resources[cfg.resource].symbol
    print(f"{nsl.metrics[cfg.metric]} {cfg.target:g} by {cfg.resource} ({symbol}), "
          f"{nsl.bootstrap_level:.0%} intervals from the bootstrap refits:")
    for entry in entries:
        print("  " + describe_need(entry, symbol))
    print_cheapest(sweep_dir, cfg, nsl)
    return 0


def print_cheapest(sweep_dir: Path, cfg: DictConfig, nsl: Nsl) -> None:
    """The cheapest configuration of every (system, arch) for the target, by its joint law (nsl.joint)."""
    results, launch = read_results(sweep_dir), launch_settings(read_launch_config(sweep_dir))
    calibration, joint = calibration_of(sweep_dir, launch, results), nsl.joint
    found = cheapest_configurations(sweep_dir, results, launch, cfg.metric, cfg.target, calibration, joint,
                                    nsl.bootstrap_level)
    length = study_named(launch.study.name).length_axis
    print(f"\n{nsl.metrics[cfg.metric]} {cfg.target:g} at the least cost, by a joint law over model size p, data d "
          f"and {length} n (nsl.joint); cost: the planner's seconds of the configuration trained alone x "
          f"{calibration:.2f} (this sweep's measured over predicted core-hours), {nsl.bootstrap_level:.0%} "
          f"interval from {joint.bootstrap} refits on resampled configurations:")
    for entry in found:
        print("\n".join("  " + line for line in ([entry] if isinstance(entry, str) else describe_cheapest(entry))))


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="predict")
