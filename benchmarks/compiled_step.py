"""The compiled training step against the eager one, both studies: prints figures and the cost values they give.

    python benchmarks/compiled_step.py [--archs unstructured ... narx subnet] [--sizes 2x1 8x2 16x4]
                                       [--models 32] [--blocks 4]

For each architecture and size (n_h x n_d), K models train in lockstep (input-state: ball, 2 trajectories;
input-output: the Silverbox stand-in, 4,000 training points, SUBNET simulating its T = 150 steps), eagerly and
compiled (``compile=always``: torch.compile of the step, Inductor), one block of steps after another (32 or 16),
in one process; the fastest block of each counts. The first compiled block minus the first eager one is the
compile time: measured with an empty kernel cache (cold: the first job of a sweep to meet the shape) and again
in a second process with the cache the first one filled (warm: every later job). Prints per row: eager and
compiled ms per step, their ratio, compile seconds cold and warm; then per architecture the values for
``cost.compile_speedup`` (the median ratio) and ``cost.compile_s`` (the largest cold compile plus log2 K warm
ones: a group recompiles as its stack halves) of conf/launch.yaml. One thread, as a task.
"""

import argparse
import itertools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

import torch

from nsl_hpc.cache import ArrayCache
from nsl_hpc.config import compose_config, plain
from nsl_hpc.models import build_model
from nsl_hpc.studies.input_output import lockstep as io_lockstep
from nsl_hpc.studies.input_output.data import load_benchmark
from nsl_hpc.studies.input_output.study import build_io_model, horizon
from nsl_hpc.studies.input_output.training import SignalScaling
from nsl_hpc.studies.input_state import lockstep
from nsl_hpc.studies.input_state.data import build_training_set
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.training import StepCompiler
from nsl_hpc.systems import SYSTEMS

INPUT_OUTPUT = ("narx", "subnet")


def input_state_run(arch: str, width: int, depth: int, models: int, blocks: int, data_dir: str
                    ) -> tuple[Callable[[StepCompiler, Callable[[], None]], object], int]:
    """``train(compiler, on_progress)`` of K ball models for ``blocks`` blocks, and the steps of a block."""
    cfg = compose_config(["system=ball", f"arch={arch}"])
    system = SYSTEMS["ball"]
    data = build_training_set(plain(cfg.system), 0, 2.0, ArrayCache(data_dir))  # 8 batches an epoch
    epochs = math.ceil(blocks * lockstep.BLOCK_STEPS / 8)
    members = []
    for k in range(models):
        torch.manual_seed(k)
        model = build_model(cfg.arch, system.state_dim, system.input_dim, width, depth)
        members.append(lockstep.Member(model, data, Scaling.fit(data, False), epochs, k))
    train = plain(cfg.train, resolve=False)
    return (lambda compiler, on_progress: lockstep.train_lockstep(members, train, on_progress, None, compiler),
            lockstep.BLOCK_STEPS)


def input_output_run(arch: str, width: int, depth: int, models: int, blocks: int, data_dir: str
                     ) -> tuple[Callable[[StepCompiler, Callable[[], None]], object], int]:
    """``train(compiler, on_progress)`` of K Silverbox stand-in models for ``blocks`` blocks, and the iterations
    of a block."""
    cfg = compose_config(["study=input_output", "system=silverbox_sim", f"arch={arch}"])
    system = plain(cfg.system)
    record = load_benchmark(system, ArrayCache(data_dir)).train.head(4000)
    scaling, base = SignalScaling.fit(record), {"system": system, "arch": plain(cfg.arch, resolve=False)}
    members = []
    for k in range(models):
        torch.manual_seed(k)
        members.append(io_lockstep.IOMember(build_io_model(base["arch"], system, width, depth), record, scaling,
                                            blocks * io_lockstep.BLOCK_STEPS, k))
    train = plain(cfg.train, resolve=False)
    return (lambda compiler, on_progress: io_lockstep.train_lockstep(members, train, horizon(base), on_progress,
                                                                     None, compiler), io_lockstep.BLOCK_STEPS)


def measure(arch: str, width: int, depth: int, models: int, blocks: int, data_dir: str) -> dict[str, float]:
    """Eager and compiled seconds per step (fastest block after the first) and the compile seconds of one shape."""
    torch.set_num_threads(1)
    build = input_output_run if arch in INPUT_OUTPUT else input_state_run
    train, block = build(arch, width, depth, models, blocks + 1, data_dir)
    seconds = {}
    for compiled in (False, True):
        compiler, ends = StepCompiler(compiled), [time.perf_counter()]
        train(compiler, lambda: ends.append(time.perf_counter()))  # noqa: B023
        if compiler.enabled != compiled:
            raise SystemExit("compiling failed (see the warning above): nothing to measure")
        seconds[compiled] = [after - before for before, after in itertools.pairwise(ends)]
    return {"eager_s": min(seconds[False][1:]) / block, "compiled_s": min(seconds[True][1:]) / block,
            "compile_s": seconds[True][0] - seconds[False][0]}


def measured(command: list[str], env: dict[str, str]) -> dict[str, float]:
    """The figures a measuring process prints (its last line); its error output and exit when it fails."""
    result = subprocess.run(command, capture_output=True, text=True, env=env)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command[2:])} failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=int, default=32, help="K, models in lockstep (lockstep.size)")
    parser.add_argument("--sizes", nargs="+", default=["2x1", "8x2", "16x4"], help="n_h x n_d")
    parser.add_argument("--archs", nargs="+", default=["unstructured", "input_affine", "port_hamiltonian"])
    parser.add_argument("--blocks", type=int, default=4, help="timed blocks of steps, after the first")
    parser.add_argument("--one", nargs=4, metavar=("ARCH", "WIDTH", "DEPTH", "DATA_DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # a measuring process (the kernel cache is its environment's)
        arch, width, depth, data_dir = args.one
        print(json.dumps(measure(arch, int(width), int(depth), args.models, args.blocks, data_dir)))
        return
    print(f"K = {args.models} models in lockstep, one thread, torch {torch.__version__}")
    print(f"{'arch':<18}{'n_h x n_d':>10}{'eager ms':>10}{'compiled ms':>13}{'ratio':>7}{'compile cold s':>16}"
          f"{'warm s':>8}", flush=True)
    results: dict[str, list[tuple[float, float, float]]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for arch in args.archs:
            for size in args.sizes:
                width, depth = size.split("x")
                with tempfile.TemporaryDirectory(dir=scratch) as kernels:  # cold, then warm: one cache per row
                    command = [sys.executable, __file__, "--models", str(args.models), "--blocks", str(args.blocks),
                               "--one", arch, width, depth, scratch]
                    cold, warm = (measured(command, {**os.environ, "TORCHINDUCTOR_CACHE_DIR": kernels})
                                  for _ in range(2))
                ratio = cold["eager_s"] / cold["compiled_s"]
                results.setdefault(arch, []).append((ratio, cold["compile_s"], warm["compile_s"]))
                print(f"{arch:<18}{size:>10}{cold['eager_s'] * 1e3:>10.2f}{cold['compiled_s'] * 1e3:>13.2f}"
                      f"{ratio:>7.2f}{cold['compile_s']:>16.1f}{warm['compile_s']:>8.1f}", flush=True)
    print("\ncost values (conf/launch.yaml):")
    print("  compile_speedup: {" + ", ".join(f"{arch}: {statistics.median(r for r, _, _ in rows):.2f}"
                                             for arch, rows in results.items()) + "}")
    shapes = math.log2(args.models)
    print("  compile_s: {" + ", ".join(f"{arch}: {max(c for _, c, _ in rows) + shapes * max(w for _, _, w in rows):.0f}"
                                       for arch, rows in results.items()) + "}")


if __name__ == "__main__":
    main()
