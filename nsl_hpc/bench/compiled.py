"""The compiled part of ``python -m nsl_hpc.bench``: compiled against eager lockstep steps, both studies.

For each shape of ``compiled.shapes`` (architecture, n_h, n_d, K), K models train in lockstep (input-state: the
bench's system and training data; input-output: ``io.system``, its first ``io.train_points`` samples, SUBNET
simulating its T steps), eagerly and compiled (``compile=always``: torch.compile of the step, Inductor), one
block of steps after another, in one process; the fastest block of each counts. The first compiled block minus
the first eager one is the compile time, measured twice in fresh processes: with an empty kernel cache (cold:
the first job of a sweep to meet the shape) and with the cache the first one filled (warm: every later job;
"cache hit" when it wrote no new compiled graph). Per row: ms per step eager and compiled, their ratio, compile
seconds cold and warm, the achieved share of this core's dense-matmul peak (about 6 p flops per sample and
model step; SUBNET's per simulated step). Then the ``cost.compile_speedup`` (median ratio) and
``cost.compile_s`` (the largest cold compile plus log2 K warm ones: a group recompiles as its stack halves)
these give, and where one block of the ``compiled.profile`` shape spends its time (torch.profiler): batched
matmuls, Inductor's fused kernels, other ATen operations, and the rest (Python, autograd and dispatch).
One thread, as a task.

    python -m nsl_hpc.bench parts=[compiled]
"""

import itertools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

from nsl_hpc.bench.measure import matmul_peak_flops
from nsl_hpc.bench.settings import BenchSettings
from nsl_hpc.config import compose_config
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import parameter_count
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_output import lockstep as io_lockstep
from nsl_hpc.studies.input_output.data import load_benchmark
from nsl_hpc.studies.input_output.study import InputOutputPair, build_io_model, horizon
from nsl_hpc.studies.input_output.training import SignalScaling
from nsl_hpc.studies.input_state import lockstep
from nsl_hpc.studies.input_state.data import build_training_set
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.input_state.study import system_dimensions
from nsl_hpc.studies.training import StepCompiler

INPUT_OUTPUT = ("narx", "subnet")
MATMULS = ("aten::bmm", "aten::baddbmm", "aten::mm", "aten::addmm")
FUSED = "CompiledFxGraph"  # the profiler's name of a call into Inductor's generated code

Train = Callable[[StepCompiler, Callable[[], None]], object]


@dataclass(frozen=True)
class Shape:
    """One shape measured (``compiled.shapes``) with what its process needs: the bench's systems and data (input-state
    ``system``, ``n_traj`` trajectories; input-output ``io_system``, its first ``io_points`` samples from
    ``data_dir``), the trajectory cache, the blocks timed, and whether one more block is profiled."""

    arch: str
    width: int
    depth: int
    models: int
    system: str
    n_traj: float
    io_system: str
    io_points: int
    data_dir: str
    data_cache: str
    blocks: int
    profile: bool


def input_state_run(shape: Shape) -> tuple[Train, int, float]:
    """``train(compiler, on_progress)`` of K input-state models, the steps of a block and the flops of a step."""
    pair = pair_of(compose_config([f"system={shape.system}", f"arch={shape.arch}"]))
    data = build_training_set(pair.system, 0, shape.n_traj, ArrayCache(shape.data_cache))
    train = pair.train
    batches = math.ceil(len(data) / train.batch_size)
    members = []
    for k in range(shape.models):
        torch.manual_seed(k)
        model = build_model(pair.arch, *system_dimensions(pair.system), shape.width, shape.depth)
        members.append(lockstep.Member(model, data, Scaling.fit(data, False),
                                       math.ceil(shape.blocks * lockstep.BLOCK_STEPS / batches), k))
    flops = 6.0 * parameter_count(members[0].model) * train.batch_size * shape.models
    return (lambda compiler, on_progress: lockstep.train_lockstep(members, train, on_progress, None, compiler),
            lockstep.BLOCK_STEPS, flops)


def input_output_run(shape: Shape) -> tuple[Train, int, float]:
    """``train(compiler, on_progress)`` of K input-output models, the iterations of a block and the flops of one."""
    pair = pair_of(compose_config(["study=input_output", f"system={shape.io_system}", f"arch={shape.arch}",
                                   f"data_dir={shape.data_dir}"]))
    assert isinstance(pair, InputOutputPair)
    record = load_benchmark(pair.system, ArrayCache(shape.data_cache)).train.head(shape.io_points)
    scaling, steps = SignalScaling.fit(record), horizon(pair)
    members = []
    for k in range(shape.models):
        torch.manual_seed(k)
        members.append(io_lockstep.IOMember(build_io_model(pair.arch, pair.system, shape.width, shape.depth),
                                            record, scaling, shape.blocks * io_lockstep.BLOCK_STEPS, k, steps))
    train = pair.train
    flops = 6.0 * members[0].model.counted_parameters() * train.batch_size * steps * shape.models
    return (lambda compiler, on_progress: io_lockstep.train_lockstep(members, train, on_progress, None, compiler),
            io_lockstep.BLOCK_STEPS, flops)


def time_shares(table: Any, wall_s: float) -> dict[str, float]:
    """Shares of ``wall_s`` in a profile's operations (``key_averages()``, self CPU time): batched matmuls,
    Inductor's fused kernels, other ATen operations, and the rest."""
    seconds = {"matmul": 0.0, "fused kernels": 0.0, "other ATen": 0.0}
    for event in table:
        kind = ("matmul" if event.key in MATMULS else "fused kernels" if FUSED in event.key
                else "other ATen" if event.key.startswith("aten::") else None)
        if kind:
            seconds[kind] += event.self_cpu_time_total / 1e6
    shares = {kind: value / wall_s for kind, value in seconds.items()}
    return {**shares, "Python, autograd, dispatch": max(0.0, 1.0 - sum(shares.values()))}


def timed_blocks(train: Train, compiled: bool, profiled: int | None) -> tuple[list[float], dict[str, float]]:
    """Seconds of each block of ``train`` eager or compiled, and with ``profiled`` (a block's index) the time
    shares of that block, left out of the seconds."""
    compiler, ends, profiler = StepCompiler(compiled), [time.perf_counter()], profile(activities=[ProfilerActivity.CPU])

    def on_progress() -> None:
        if len(ends) == profiled:  # the next block is profiled
            profiler.__enter__()
        ends.append(time.perf_counter())

    train(compiler, on_progress)
    if compiler.enabled != compiled:
        raise SystemExit("compiling failed (see the warning above): nothing to measure")
    durations = [after - before for before, after in itertools.pairwise(ends)]
    if profiled is None:
        return durations, {}
    profiler.__exit__(None, None, None)
    return durations[:profiled], time_shares(profiler.key_averages(), durations[profiled])


def measure(shape: Shape) -> dict[str, Any]:
    """Eager and compiled seconds per step (fastest block after the first), the compile seconds of one shape,
    the flops of a step, and with ``shape.profile`` the time shares of one more block each way."""
    torch.set_num_threads(1)
    build = input_output_run if shape.arch in INPUT_OUTPUT else input_state_run
    blocks = shape.blocks + 1
    train, block, flops = build(replace(shape, blocks=blocks + shape.profile))
    profiled = blocks if shape.profile else None
    (eager, eager_shares), (compiled, compiled_shares) = (timed_blocks(train, mode, profiled) for mode in (False, True))
    shares = {"eager": eager_shares, "compiled": compiled_shares} if shape.profile else {}
    return {"eager_s": min(eager[1:]) / block, "compiled_s": min(compiled[1:]) / block,
            "compile_s": compiled[0] - eager[0], "flops": flops, "shares": shares}


def fxgraph_entries(cache: Path) -> int:
    """Compiled graphs in an Inductor cache directory."""
    return sum(1 for _ in cache.glob("fxgraph/*/*/*"))


def measured(shape: Shape, kernels: Path) -> dict[str, Any]:
    """``measure(shape)`` in a fresh process with the kernel cache ``kernels``; its error output when it fails."""
    command = [sys.executable, "-m", "nsl_hpc.bench.compiled", json.dumps(asdict(shape))]
    result = subprocess.run(command, capture_output=True, text=True,
                            env={**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(kernels)})
    if result.returncode != 0:
        raise SystemExit(f"measuring {shape.arch} failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.splitlines()[-1])


def shape_row(shape: Shape, scratch: Path, peak: float) -> dict[str, Any]:
    """One table row: a cold and a warm (cache) measurement of ``shape``."""
    with tempfile.TemporaryDirectory(dir=scratch) as folder:
        kernels = Path(folder)
        cold = measured(shape, kernels)
        entries = fxgraph_entries(kernels)
        warm = measured(replace(shape, profile=False), kernels)
        hit = fxgraph_entries(kernels) == entries
    return {"arch": shape.arch, "width": shape.width, "depth": shape.depth, "models": shape.models,
            "eager_ms": cold["eager_s"] * 1e3, "compiled_ms": cold["compiled_s"] * 1e3,
            "ratio": cold["eager_s"] / cold["compiled_s"], "compile_cold_s": cold["compile_s"],
            "compile_warm_s": warm["compile_s"], "cache_hit": hit,
            "peak_eager": cold["flops"] / cold["eager_s"] / peak,
            "peak_compiled": cold["flops"] / cold["compiled_s"] / peak, "shares": cold["shares"]}


def cost_values(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """``cost.compile_speedup`` and ``cost.compile_s`` per architecture (conf/launch.yaml)."""
    speedup: dict[str, float] = {}
    compile_s: dict[str, float] = {}
    for arch in dict.fromkeys(row["arch"] for row in rows):
        own = [row for row in rows if row["arch"] == arch]
        speedup[arch] = round(statistics.median(row["ratio"] for row in own), 2)
        compile_s[arch] = round(max(row["compile_cold_s"] for row in own) + max(
            math.log2(row["models"]) * row["compile_warm_s"] for row in own))
    return {"compile_speedup": speedup, "compile_s": compile_s}


def report(rows: list[dict[str, Any]], costs: Mapping[str, Mapping[str, float]], peak: float, blocks: int) -> str:
    """The figures as markdown (docs/performance.md's compiled table)."""
    lines = [f"Measured by `python -m nsl_hpc.bench parts=[compiled]` on one core (1 thread), torch "
             f"{torch.__version__}; eager and compiled in one process, the fastest of {blocks} blocks "
             f"each; compile seconds cold (an empty kernel cache) and warm (a second process on the cache the first "
             f"filled). Dense float32 matmul peak: {peak / 1e9:.1f} GFLOP/s.", "",
             "| arch | K | n_h x n_d | eager ms / step | compiled ms / step | ratio | compile cold s | warm s | "
             "cache hit | % of matmul peak, eager / compiled |", "|---|---:|---|---:|---:|---:|---:|---:|---|---:|"]
    for row in rows:
        lines.append(f"| {row['arch']} | {row['models']} | {row['width']} x {row['depth']} | {row['eager_ms']:.2f} | "
                     f"{row['compiled_ms']:.2f} | {row['ratio']:.2f} | {row['compile_cold_s']:.1f} | "
                     f"{row['compile_warm_s']:.1f} | {'yes' if row['cache_hit'] else 'no'} | "
                     f"{100 * row['peak_eager']:.1f} / {100 * row['peak_compiled']:.1f} |")
    lines += ["", "Cost values they give (conf/launch.yaml `cost`): " + "; ".join(
        f"{key}: {{{', '.join(f'{arch}: {value}' for arch, value in values.items())}}}"
        for key, values in costs.items()) + "."]
    for row in rows:
        if row["shares"]:
            lines += ["", f"Where a step of {row['arch']} (K = {row['models']}, n_h {row['width']}, n_d "
                      f"{row['depth']}) spends its time (torch.profiler, one block):", "",
                      "| | " + " | ".join(row["shares"]["eager"]) + " |",
                      "|---|" + "---:|" * len(row["shares"]["eager"])]
            lines += [f"| {mode} | " + " | ".join(f"{100 * share:.0f}%" for share in shares.values()) + " |"
                      for mode, shares in row["shares"].items()]
    return "\n".join(lines)


def compiled_part(bench: BenchSettings, root: Path) -> tuple[str, dict[str, Any]]:
    """The compiled table and its headline figures (``compiled_*`` keys)."""
    peak, compiled, io = matmul_peak_flops(bench.matmul_size), bench.compiled, bench.io
    rows = []
    for arch, shapes in compiled.shapes.items():
        for width, depth, models in shapes:
            shape = Shape(arch, width, depth, models, bench.system.name, bench.n_traj, io.system, io.train_points,
                          io.data_dir, str(root / "data"), compiled.blocks,
                          [arch, width, depth, models] == compiled.profile)
            rows.append(shape_row(shape, root, peak))
            print(f"compiled: {arch} {width} x {depth}, K {models}: {rows[-1]['ratio']:.2f}x", file=sys.stderr,
                  flush=True)
    costs = cost_values(rows)
    return report(rows, costs, peak, compiled.blocks), {"compiled": rows, "compiled_cost": costs}


if __name__ == "__main__":  # a measuring process: python -m nsl_hpc.bench.compiled '<spec as JSON>'
    print(json.dumps(measure(Shape(**json.loads(sys.argv[1])))))
