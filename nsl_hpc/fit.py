"""Fit a broken NSL to every (system, arch, resource, metric) of a merged sweep.

    python -m nsl_hpc.fit sweep_dir=runs/demo [nsl.max_breaks=3] [nsl.objective=study]
    python -m nsl_hpc.fit sweep_dir=runs/io metrics=[nmse,nmse_one_step_test,rmse_mv_free_run_arrow_full]

Reads ``<sweep_dir>/results.parquet`` (``python -m nsl_hpc.merge``) and writes ``<sweep_dir>/nsl_fits.parquet``
(one row per NSL: system, arch, resource, metric, b, alpha, beta, delta0, sigma_i, phi_i, delta_i, margin,
formula, extrapolation backtest), ``<sweep_dir>/nsl_fits.txt`` and a card per law,
``<sweep_dir>/law_cards/<system>__<arch>__<resource>__<metric>.json`` (the grid and its hash, the envelope and
its points, b and why, M, intervals, backtest, the published law, code version, predicted and measured
core-hours: what it takes to reproduce or reject the law). It prints, per (system, arch), the share of tasks no
better than the mean predictor, flagging a pair whose models do not learn (``nsl.learning``). Only tasks with
status ok and finite,
positive errors are fitted; an NSL that cannot be fitted gets its reason in the ``error`` column. ``metrics``
picks the results columns fitted (default: ``nsl.metrics``, nmae and nmse), e.g. an input-output sweep's extra
scores (``<metric>_<mode>_<record>``).
"""

from pathlib import Path

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.analysis.fitted import fit_and_record
from nsl_hpc.analysis.fitting import fits_path
from nsl_hpc.analysis.learning import learning_lines
from nsl_hpc.analysis.nsl_settings import nsl_settings
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, require_sweep


def main(cfg: DictConfig) -> int:
    nsl = nsl_settings(cfg.nsl)
    sweep_dir = require_sweep(cfg.sweep_dir)
    fitted = fit_and_record(sweep_dir, nsl, cfg.metrics, cfg.workers, launch_settings(read_launch_config(sweep_dir)))
    print("\n".join(learning_lines(fitted.learning)))
    rows = fitted.rows
    failed = sum(row["error"] is not None for row in rows)
    print(f"{len(rows) - failed} NSLs fitted ({failed} not fittable) -> {fits_path(sweep_dir)}, "
          f"{Path(sweep_dir) / layout.FITS_TEXT}, a card per law in {Path(sweep_dir) / layout.LAW_CARDS}")
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="fit")
