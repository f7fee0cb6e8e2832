"""Post-processing benchmark: prints figures, asserts nothing.

    python benchmarks/postprocess_bench.py

On a synthetic 63,504-task input-state sweep (97% of rows written, 3% failure records):
1. merging the 63,504 shards into results.parquet (target < 30 s), again (idempotent), and with 10 corrupt
   shards (the slow path that finds them);
2. fitting its 54 NSLs with nsl.bootstrap refits each (all cores; target <= 5 minutes on 2 cores), and the
   margins of the default fit against the study's objective (without bootstrap).
"""

import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from synthetic import corrupt_rows, fill_sweep, synthetic_input_state_sweep

from nsl_hpc.analysis.fitting import fit_sweep
from nsl_hpc.analysis.nsl_settings import nsl_settings
from nsl_hpc.bench.measure import timed
from nsl_hpc.config import compose_config
from nsl_hpc.sweep.merge import merge_sweep, results_path


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        sweep_dir = synthetic_input_state_sweep(Path(tmp) / "input_state")
        (rows, failures), fill_s = timed(fill_sweep, sweep_dir)
        print(f"synthetic sweep: {rows:,} rows and {failures:,} failure records written in {fill_s:.0f} s")
        summary, first_s = timed(merge_sweep, sweep_dir)
        table = pq.read_table(results_path(sweep_dir))
        _, second_s = timed(merge_sweep, sweep_dir)
        same = pq.read_table(results_path(sweep_dir)).equals(table)
        print(f"merge: {summary.merged:,} of {summary.tasks:,} tasks in {first_s:.1f} s (target 30 s); again in "
              f"{second_s:.1f} s, identical table: {same}")
        print("       " + summary.describe().replace("\n", "\n       "))
        corrupt_rows(sweep_dir, 10)
        summary, corrupt_s = timed(merge_sweep, sweep_dir)
        print(f"merge with 10 corrupt shards: {corrupt_s:.1f} s, {len(summary.corrupt_shards)} reported, "
              f"{summary.merged:,} merged")

        results = pq.read_table(results_path(sweep_dir))
        nsl = nsl_settings(compose_config([f"sweep_dir={sweep_dir}"], "fit").nsl)
        fits, fit_s = timed(fit_sweep, results, nsl, None)
        print(f"fit: {len(fits)} NSLs on {results.num_rows:,} outcomes with {nsl.bootstrap} bootstrap refits each in "
              f"{fit_s:.0f} s on {os.cpu_count()} cores (target 300 s; b chosen: {sorted(f['b'] for f in fits)})")
        study_cfg = dataclasses.replace(nsl, objective="study", bootstrap=0)
        study, study_s = timed(fit_sweep, results, study_cfg, None)
        ratios = np.array([s["margin"] / d["margin"] for d, s in zip(fits, study, strict=True)])
        print(f"objective: the study's Adam fit ({study_s:.0f} s) has a margin {np.median(ratios):.1f}x the "
              f"default's (median; range {ratios.min():.2f}-{ratios.max():.1f}x); default lower in "
              f"{(ratios > 1).sum()} of {len(ratios)} NSLs")


if __name__ == "__main__":
    main()
