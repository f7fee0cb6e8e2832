"""How close the default fit comes to the least margin objective (Definition 1's margin, a residual where the law
lies above the envelope weighed nsl.above_weight), and how it chooses b, on outcome clouds of known laws
(tests/fit_clouds.py): the paper's ten laws, random laws in their style, and 0- and 1-break laws.

    .venv/bin/python benchmarks/fit_quality.py [--n 3000] [--random 6] [--envelopes step interpolated]

Per cloud and envelope: the objective (on Definition 1's step envelope) of the fit with the true b over the direct
multi-start fit's; b chosen automatically; the backtest (fitted below the middle of the log range, scored
above it: mean squared log error). Fits with 200 bootstrap resamples are timed by benchmarks/postprocess_bench.py.
"""

import argparse
import time

import numpy as np

from nsl_hpc.nsl import backtest_nsl, default_settings, fit_nsl
from tests.fit_clouds import b_acceptable, cloud, direct_objective, law, objective_of, published_shapes, random_shapes


def shapes(random: int) -> dict:
    plain = {"b0: power law": (law(0.0, 3.0, -0.3), 1e2, 1e8),
             "b1: saturating": (law(0.01, 3.0, -0.2, (1e5, 0.2, -1.0)), 1e2, 1e9)}
    return plain | published_shapes() | random_shapes(random, seed=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=7056,
                        help="outcomes per cloud (the study: 7 x 1,008 per system and architecture)")
    parser.add_argument("--random", type=int, default=8, help="random laws in the published style")
    parser.add_argument("--envelopes", nargs="+", default=["step", "interpolated"])
    parser.add_argument("--seed", type=int, default=0, help="the clouds' first seed (each cloud its own)")
    args = parser.parse_args()
    cells = (f"{envelope}: objective / direct, b chosen, backtest, s" for envelope in args.envelopes)
    header = "| cloud | b | " + " | ".join(cells) + " |"
    print(header)
    print("|" + "---|" * (2 + len(args.envelopes)))
    ratios, backtests = ({e: [] for e in args.envelopes} for _ in range(2))
    chosen_ok = 0
    clouds = shapes(args.random)
    for seed, (name, (true, low, high)) in enumerate(clouds.items(), start=args.seed):
        r, e = cloud(true, low, high, args.n, seed)
        reference = direct_objective(r, e, true.b)
        cells = []
        for envelope in args.envelopes:
            settings = default_settings(envelope=envelope)
            start = time.perf_counter()
            given = fit_nsl(r, e, breaks=true.b, settings=settings)
            chosen = fit_nsl(r, e, settings=settings)
            seconds = time.perf_counter() - start
            cut = float(np.exp((np.log(r.min()) + np.log(r.max())) / 2))
            backtest = backtest_nsl(r, e, cut, settings=settings).margin
            ratio = objective_of(given, r, e) / reference
            ratios[envelope].append(ratio)
            backtests[envelope].append(backtest)
            chosen_ok += envelope == args.envelopes[0] and b_acceptable(chosen.b, true.b)
            cells.append(f"{ratio:.2f}, {chosen.b}, {backtest:.3f}, {seconds:.1f}")
        print(f"| {name} | {true.b} | " + " | ".join(cells) + " |", flush=True)
    for envelope, values in ratios.items():
        print(f"{envelope}: objective / direct median {np.median(values):.2f}, max {np.max(values):.2f}; "
              f"backtest median {np.median(backtests[envelope]):.3f}")
    print(f"b chosen ({args.envelopes[0]}): {chosen_ok} of {len(clouds)} clouds within 1 of the true b "
          "(0- and 1-break clouds: no extra break)")


if __name__ == "__main__":
    main()
