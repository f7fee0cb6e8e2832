"""The compiled input-state training step against the eager one: prints figures and the cost values they give.

    python benchmarks/compiled_step.py [--models 32] [--sizes 2x1 8x2 16x4] [--archs unstructured ...] [--blocks 4]

For each architecture and size (n_h x n_d), K ball models train in lockstep on 2 trajectories, once eagerly and
once compiled (``compile=always``: torch.compile of the step, Inductor), in one process, block for block
interleaved (the fastest block of each counts, so a busy core slows both alike). The first compiled block minus
an eager one is the compile time: measured with an empty kernel cache (cold, the first job of a sweep to meet
the shape) and again in a second process with the cache the first one filled (warm, every later job). Prints per
row: eager and compiled ms per step, their ratio, compile seconds cold and warm; then per architecture the
values for ``cost.compile_speedup`` (the median ratio) and ``cost.compile_s`` (the largest cold compile plus
log2 K warm ones: a group recompiles as its stack halves) of conf/launch.yaml. One thread, as a task.
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time

import torch

from nsl_hpc.cache import ArrayCache
from nsl_hpc.config import compose_config, plain
from nsl_hpc.models import build_model
from nsl_hpc.studies.input_state.data import build_training_set
from nsl_hpc.studies.input_state.lockstep import BLOCK_STEPS, Lockstep, Member
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.training import StepCompiler
from nsl_hpc.systems import SYSTEMS


def measure(arch: str, width: int, depth: int, models: int, blocks: int, data_dir: str) -> dict[str, float]:
    """Eager and compiled seconds per step (fastest block of ``blocks``) and the compile seconds of one shape."""
    torch.set_num_threads(1)
    cfg = compose_config(["system=ball", f"arch={arch}"])
    system = SYSTEMS["ball"]
    data = build_training_set(plain(cfg.system), 0, 2.0, ArrayCache(data_dir))
    members = []
    for k in range(models):
        torch.manual_seed(k)
        model = build_model(cfg.arch, system.state_dim, system.input_dim, width, depth)
        members.append(Member(model, data, Scaling.fit(data, False), 10_000, k))
    train = plain(cfg.train, resolve=False)
    runs = {compiled: Lockstep(members, train, StepCompiler(compiled)) for compiled in (False, True)}
    first: dict[bool, float] = {}
    best = {False: math.inf, True: math.inf}
    for block in range(blocks + 1):
        for compiled, run in runs.items():
            started = time.perf_counter()
            run.train_block(block * BLOCK_STEPS, BLOCK_STEPS, lambda *_: None)
            seconds = time.perf_counter() - started
            if block == 0:
                first[compiled] = seconds
            else:
                best[compiled] = min(best[compiled], seconds / BLOCK_STEPS)
    if not runs[True].compiler.enabled:
        raise SystemExit("compiling failed (see the warning above): nothing to measure")
    return {"eager_s": best[False], "compiled_s": best[True], "compile_s": first[True] - first[False]}


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
    parser.add_argument("--blocks", type=int, default=4, help=f"timed blocks of {BLOCK_STEPS} steps")
    parser.add_argument("--one", nargs=4, metavar=("ARCH", "WIDTH", "DEPTH", "DATA_DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # a measuring process (the kernel cache is its environment's)
        arch, width, depth, data_dir = args.one
        print(json.dumps(measure(arch, int(width), int(depth), args.models, args.blocks, data_dir)))
        return
    print(f"K = {args.models} ball models, 2 trajectories, one thread, torch {torch.__version__}")
    print(f"{'arch':<18}{'n_h x n_d':>10}{'eager ms':>10}{'compiled ms':>13}{'ratio':>7}{'compile cold s':>16}"
          f"{'warm s':>8}")
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
