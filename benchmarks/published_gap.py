"""How far a sweep's step envelope (Definition 1's: the least error of any outcome at or below a resource) lies
above a published law, at chosen resources, for each score column; prints a table, asserts nothing. The
controlled experiments of docs/reproduction.md ("What each change moved") read it.

    python benchmarks/published_gap.py runs/exp/plateau_10s [more sweep dirs] \
        [--law ball/input_affine/compute/nmae] [--at 3e4 1e5 3e5 1e6 3e6 1e7 2e7] \
        [--columns nmae_scalar nmae_per_column] [--below 0.25] [--resource-column flops_paper] [--repeat 8]

Each sweep must be merged (results.parquet). The published law is the one of ``--law`` in
conf/published_laws.yaml; ``--columns`` are results columns of the same metric (default: every column whose
name starts with the law's metric). A cell is envelope / law at that resource; "-" where no outcome lies at or
below it. The last column is the least resource at which the envelope is below ``--below`` (the published law's
in the header).

``--repeat R`` (input-state sweeps of one pass per epoch) reads each outcome approximately as the authors' 2026
``--repeat R`` would have logged it: their main.py concatenates the training set R times and trains the given
epochs over it, while the compute formula counts the epochs alone. A task of n_e epochs then stands for a logged
run of n_e / R epochs (tasks with n_e / R below the grid's smallest epoch count, 2, are left out) and its
resource is divided by R (compute) or kept (data, model). Approximately: n_e epochs take n_e ceil(N / B) steps,
n_e / R epochs over the joined data (n_e / R) ceil(R N / B), the same only where B divides N (not below N = 256).
A sweep trained with ``train.repeat`` > 1 is read as it is, without this option.
"""

import argparse
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from nsl_hpc.analysis.published import published_laws, resource_columns, step_envelope_at


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", nargs="+", type=Path)
    parser.add_argument("--law", default="ball/input_affine/compute/nmae")
    parser.add_argument("--at", nargs="+", type=float, default=[3e4, 1e5, 3e5, 1e6, 3e6, 1e7, 2e7])
    parser.add_argument("--columns", nargs="*")
    parser.add_argument("--below", type=float, default=0.25)
    parser.add_argument("--resource-column", help="results column of the resource (default: flops, train_points "
                        "or params); e.g. flops_paper, the compute on the paper's 4 n_d n_h^2 parameters")
    parser.add_argument("--repeat", type=int, default=1, help="read outcomes as runs of n_e / R logged epochs "
                        "over the data repeated R times (compute divided by R)")
    args = parser.parse_args()
    system, arch, resource, metric = args.law.split("/")
    if args.repeat < 1:
        parser.error(f"--repeat {args.repeat}: a positive integer")
    law = published_laws()[system, arch, resource, metric].law
    at = np.asarray(args.at)
    dense = np.geomspace(1e2, 1e13, 4000)
    crossing = dense[np.argmax(law.predict(dense) < args.below)] if np.any(law.predict(dense) < args.below) else None
    print(f"step envelope / published law ({args.law}) at {resource} = " + ", ".join(f"{r:.0e}" for r in at)
          + f"; first below {args.below:g} (published: {'-' if crossing is None else f'{crossing:.2g}'})")
    for sweep in args.sweeps:
        results = pq.read_table(sweep / "results.parquet").to_pylist()
        rows = [row for row in results if row["system"] == system and row["arch"] == arch and row["status"] == "ok"]
        if args.repeat > 1:
            if any("epochs" not in row or (row.get("repeat") or 1) != 1 for row in rows):
                parser.error(f"--repeat reads input-state rows of one pass per epoch; {sweep} holds others")
            rows = [row for row in rows if row["epochs"] >= 2 * args.repeat]
        if not rows:
            print(f"| {sweep.name} | no {system} / {arch} outcomes |")
            continue
        columns = args.columns or sorted(key for key in rows[0] if key.startswith(metric))
        r = np.array([row[args.resource_column or resource_columns()[resource]] for row in rows], dtype=float)
        if resource == "compute":
            r = r / args.repeat
        for column in columns:
            e = np.array([row.get(column, np.nan) for row in rows], dtype=float)
            ratios = step_envelope_at(r, e, at) / law.predict(at)
            cells = " | ".join("-" if np.isnan(x) else f"{x:.2f}" for x in ratios)
            below = r[e < args.below]
            first = f"{below.min():.2g}" if len(below) else f"> {r.max():.2g}"
            print(f"| {sweep.name} | {column} | {len(rows)} | {cells} | {first} |")


if __name__ == "__main__":
    main()
