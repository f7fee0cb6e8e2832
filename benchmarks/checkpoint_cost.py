"""What training checkpoints cost the largest lockstep group of the input-state study: prints figures.

    python benchmarks/checkpoint_cost.py [--models 32] [--width 32] [--depth 4] [--trajectories 64] [--blocks 4]

Trains K port-Hamiltonian models (n_h, n_d as given, spring, ``--trajectories`` of training data each, one
thread) for a few blocks, writing the group's checkpoint after every block, and prints: the checkpoint's size,
the time to write it, the training time of a block, and the share of training time checkpointing takes at the
default interval (``checkpoint.every_minutes`` of conf/launch.yaml: one write per that much training).
"""

import argparse
import tempfile
import time
from pathlib import Path

import torch

from nsl_hpc.config import compose_config
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.checkpoint import Checkpointer, read_info
from nsl_hpc.models import build_model
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_state.data import build_training_set
from nsl_hpc.studies.input_state.lockstep import BLOCK_STEPS, Member, train_lockstep
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.settings import batch_count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=int, default=32)
    parser.add_argument("--width", type=int, default=32)
    parser.add_argument("--depth", type=int, default=4)
    parser.add_argument("--trajectories", type=float, default=64)
    parser.add_argument("--blocks", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        cfg = compose_config(["system=spring", "arch=port_hamiltonian", f"cache_dir={folder}/cache"])
        system_cfg = pair_of(cfg).system
        data = build_training_set(system_cfg, 0, args.trajectories, ArrayCache(Path(folder) / "cache"))
        epochs = -(-args.blocks * BLOCK_STEPS // batch_count(len(data), cfg.train.batch_size))
        members = []
        for seed in range(args.models):
            torch.manual_seed(seed)
            model = build_model(pair_of(cfg).arch, 4, 2, width=args.width, depth=args.depth)
            members.append(Member(model, data, Scaling.fit(data, rescale_targets=False), epochs, seed,
                                  milestones=(max(epochs // 2, 1),)))
        ids = [str(k) for k in range(len(members))]
        checkpoint = Checkpointer(Path(folder) / "group.pt", every_s=1e-9, task_ids=ids)
        blocks = []
        started = time.perf_counter()
        train_lockstep(members, pair_of(cfg).train, lambda: blocks.append(time.perf_counter()),
                       checkpoint)
        total = time.perf_counter() - started
        info = read_info(checkpoint.path)
        every_s = 60 * compose_config([], "launch").checkpoint.every_minutes
    write_s = checkpoint.write_seconds / checkpoint.writes
    block_s = (total - checkpoint.write_seconds) / len(blocks)
    print(f"group: K={args.models} port-Hamiltonian, n_h {args.width}, n_d {args.depth}, {len(data):,} samples, "
          f"{epochs} epochs ({len(blocks)} blocks of {BLOCK_STEPS} steps)")
    print(f"checkpoint: {info['bytes'] / 2**20:.2f} MiB, written in {1e3 * write_s:.1f} ms "
          f"(mean of {checkpoint.writes})")
    print(f"training: {block_s:.2f} s per block of {BLOCK_STEPS} steps")
    print(f"share of training time at checkpoint.every_minutes={every_s / 60:g}: {100 * write_s / every_s:.4f}% "
          f"(one write per {every_s:.0f} s; target < 1%); written after every block it would be "
          f"{100 * write_s / block_s:.1f}%")


if __name__ == "__main__":
    main()
