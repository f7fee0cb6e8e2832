"""Train and score one model and write its outcome as one Parquet row.

    python -m nsl_hpc.train system=ball arch=port_hamiltonian epochs=64 data_tier=8 width_tier=8 \\
        depth_tier=2 seed=3 out_dir=runs/demo
    python -m nsl_hpc.train study=input_output system=silverbox_sim arch=narx iter_multiplier=1 data_tier=250

The row lands in <out_dir>/rows/<id[:2]>/<id>.parquet. A task whose row exists is skipped (force=true
recomputes it). Bad input gets one line on stderr and exit status 2 before any work starts.
"""


from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.sweep.task import describe, run_task


def main(cfg: DictConfig) -> int:
    result = run_task(cfg)
    if result.skipped or result.row is None:
        print(f"skipped: row exists at {result.path} (force=true recomputes it)")
    else:
        print(f"{describe(result.row)} -> {result.path}")
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="one_task")
