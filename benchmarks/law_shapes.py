"""Whether a sweep's fitted laws are laws a scientist accepts: how far each rises with its resource (the largest
segment slope, and the largest local log-log slope of the law over its range), slopes at the bound, and what is
reported undetermined. Reads <sweep_dir>/nsl_fits.parquet (python -m nsl_hpc.fit or report).

    .venv/bin/python benchmarks/law_shapes.py runs/demo [runs/repro/input_state ...]

The published laws rise at most +0.19 (conf/published_laws.yaml: ball / pH / model's delta0).
"""

import argparse
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from nsl_hpc.analysis.fitting import fit_from_row
from nsl_hpc.nsl import default_settings


def local_rise(row: dict) -> float:
    """The largest d ln L / d ln r of the row's law over its fitted resource range (2,000 log-spaced points)."""
    r = np.geomspace(row["r_min"], row["r_max"], 2000)
    return float(np.max(np.diff(np.log(fit_from_row(row).predict(r))) / np.diff(np.log(r))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dirs", nargs="+", type=Path)
    args = parser.parse_args()
    bound = default_settings().max_slope
    print("| sweep | laws | b = 0/1/2/3/4 | segment rising > +0.2 | largest segment slope | largest local slope | "
          "slope at -max_slope | undetermined |")
    print("|---|---|---|---|---|---|---|---|")
    for sweep_dir in args.sweep_dirs:
        rows = [row for row in pq.read_table(sweep_dir / "nsl_fits.parquet").to_pylist() if row["error"] is None]
        slopes = [np.asarray(row["slopes"]) for row in rows]
        counts = "/".join(str(sum(row["b"] == b for row in rows)) for b in range(5))
        print(f"| {sweep_dir} | {len(rows)} | {counts} | {sum(s.max() > 0.2 for s in slopes)} | "
              f"{max(s.max() for s in slopes):+.2f} | {max(local_rise(row) for row in rows):+.3f} | "
              f"{sum(s.min() <= -bound + 0.01 for s in slopes)} | {sum(bool(row['undetermined']) for row in rows)} |")


if __name__ == "__main__":
    main()
