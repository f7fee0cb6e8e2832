"""A sweep fitted, the step ``fit`` and ``report`` share: its merged results, a law per (system, arch, resource,
metric) of the chosen metrics written beside them with a card each, and whether each pair's models learned."""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from nsl_hpc.analysis.cards import write_law_cards
from nsl_hpc.analysis.fitting import (
    choose_metrics,
    fit_sweep,
    fits_path,
    read_results,
    rehearsal_of,
    require_some_fit,
    write_fits,
)
from nsl_hpc.analysis.learning import PairLearning, sweep_learning
from nsl_hpc.analysis.nsl_settings import Nsl
from nsl_hpc.sweep.launch_settings import LaunchSettings


@dataclass(frozen=True)
class FittedSweep:
    results: pa.Table  # the merged outcomes
    nsl: Nsl  # the nsl settings with the chosen metrics
    rows: list[dict[str, Any]]  # a row per NSL (nsl_fits.parquet)
    cards: dict[str, Any]  # what write_law_cards returns
    learning: list[PairLearning]  # per (system, arch): did its models learn


def fit_and_record(sweep_dir: Path, nsl: Nsl, metrics: Sequence[str] | None, workers: int | None,
                   launch: LaunchSettings) -> FittedSweep:
    """Fit the laws of ``metrics`` (None: the nsl group's) on the sweep's merged results with ``workers``
    processes, write them (nsl_fits.parquet, fits.txt) and their cards once one law could be fitted (else raise,
    replacing nothing), and say whether each pair's models learned. ``launch``: the sweep's launch settings."""
    results = read_results(sweep_dir)
    chosen = choose_metrics(nsl, metrics, results)
    rows = fit_sweep(results, chosen, workers, rehearsal_of(launch))
    require_some_fit(rows, fits_path(sweep_dir))
    write_fits(sweep_dir, rows)
    cards = write_law_cards(sweep_dir, launch, chosen, results, rows)
    return FittedSweep(results, chosen, rows, cards, sweep_learning(results, chosen))
