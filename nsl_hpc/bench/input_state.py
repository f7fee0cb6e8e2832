"""The input-state part of ``python -m nsl_hpc.bench``: plain PyTorch loops against ours, side by side in one
process.

1. per architecture at a small and a large size: samples/s of two reference loops on the modules, the plain
   loop (random mini-batch gather, forward, the study's loss, backward, Adam step, zero_grad) and the authors'
   loop (a shuffling DataLoader, forward, loss, backward, clip_grad_norm_, Adam step, LambdaLR step,
   zero_grad), of ours alone (the lockstep loop with K = 1) and per model of ours with K models packed,
   and the ratios; the same model, data, batch size and step count;
2. where the time of one task goes: interpreter + imports, data (cache miss and hit), training, scoring, writing;
3. the achieved flop rate (about 6 p flops per sample and step) against this core's dense-matmul peak;
4. the projected core-hours of the whole input-state study, each reference loop (one process per task)
   against ours (the launcher's lockstep groups of K tasks of one system, architecture, depth and width
   bucket, by similar step counts), from per-step costs measured per (architecture, width, depth) and the
   grid's step counts; ours with epoch milestones (one model per 14 tasks that differ only in epochs, shared
   draws); and the planner's own prediction (``cost.*``, for time limits);
5. the peak memory of the largest input-state task.
"""

import copy
import dataclasses
import math
import resource
import subprocess
import sys
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from nsl_hpc.bench.measure import (
    TASK_IMPORTS,
    interpolate,
    matmul_peak_flops,
    planner_core_hours,
    study_manifest,
    timed,
)
from nsl_hpc.bench.settings import BenchSettings, TypicalTask
from nsl_hpc.config import compose_config
from nsl_hpc.config.arch import arch_settings
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import parameter_count
from nsl_hpc.studies.input_state.data import build_test_set, build_training_set
from nsl_hpc.studies.input_state.lockstep import Member, predict_derivatives, train_lockstep
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.input_state.study import system_dimensions
from nsl_hpc.studies.metrics import normalized_errors
from nsl_hpc.studies.settings import InputStateTrain, batch_count, warmup_cosine
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.plan import Grouping, lockstep_groups, training_segments, with_compile
from nsl_hpc.sweep.rows import write_row_atomically


def normalised_mse(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The study's loss term (the authors' utils.normalized_mse)."""
    return ((predicted - target) / (target.std() + 1e-6)).square().mean()


def reference_loop(model: nn.Module, member: Member, steps: int, train: InputStateTrain) -> None:
    """The plain loop a user writes: random mini-batch gather, forward, the study's loss, backward, Adam,
    zero_grad."""
    dtype = getattr(torch, train.dtype)
    z, v = member.scaling.model_inputs(member.data, dtype)
    dz, y = member.scaling.model_targets(member.data, dtype)
    optimizer = torch.optim.Adam(model.parameters(), lr=train.lr)
    generator = torch.Generator().manual_seed(member.shuffle_seed)
    for _ in range(steps):
        index = torch.randint(len(z), (train.batch_size,), generator=generator)
        predicted_dz, predicted_y = model(z[index], v[index])
        loss = normalised_mse(predicted_dz, dz[index]) + train.output_weight * normalised_mse(predicted_y, y[index])
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()


def authors_loop(model: nn.Module, member: Member, steps: int, train: InputStateTrain) -> None:
    """The authors' training loop without Lightning: a shuffling DataLoader over (x, u, dx/dt, y) samples,
    forward, loss, backward, clip_grad_norm_, Adam, LambdaLR (warm-up + cosine), zero_grad."""
    dtype = getattr(torch, train.dtype)
    z, v = member.scaling.model_inputs(member.data, dtype)
    dz, y = member.scaling.model_targets(member.data, dtype)
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(z, v, dz, y), batch_size=train.batch_size,
                                         shuffle=True, generator=torch.Generator().manual_seed(member.shuffle_seed))
    optimizer = torch.optim.Adam(model.parameters(), lr=train.lr)
    factors = warmup_cosine(steps, train.warmup_fraction, 1.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: float(factors[min(step, steps - 1)]))
    taken = 0
    while taken < steps:
        for batch_z, batch_v, batch_dz, batch_y in loader:
            predicted_dz, predicted_y = model(batch_z, batch_v)
            loss = (normalised_mse(predicted_dz, batch_dz)
                    + train.output_weight * normalised_mse(predicted_y, batch_y))
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), train.grad_clip_norm)
            optimizer.step()
            scheduler.step()
            optimizer.zero_grad()
            taken += 1
            if taken == steps:
                break


class Bench:
    """Models and data of the benchmark's system, built once."""

    def __init__(self, settings: BenchSettings, cache: ArrayCache):
        self.train, self.system = settings.train, settings.system
        self.data = build_training_set(self.system, 0, settings.n_traj, cache)
        self.scaling = Scaling.fit(self.data, self.train.rescale_targets)
        self.batches = batch_count(len(self.data), self.train.batch_size)
        self.archs = {arch: arch_settings(compose_config([f"arch={arch}"]).arch)
                      for arch in {*settings.archs, settings.typical_task.arch}}  # composed once, not per model

    def model(self, arch: str, width: int, depth: int, seed: int) -> nn.Module:
        torch.manual_seed(seed)
        return build_model(self.archs[arch], *system_dimensions(self.system), width, depth)

    def members(self, arch: str, width: int, depth: int, count: int, steps: int) -> list[Member]:
        epochs = max(1, math.ceil(steps / self.batches))
        return [Member(self.model(arch, width, depth, k), self.data, self.scaling, epochs, k) for k in range(count)]

    def step_seconds(self, arch: str, width: int, depth: int, steps: int, pack: int) -> dict[str, float]:
        """Seconds per optimizer step: the plain reference loop, the authors' loop, ours alone, ours for ``pack``
        models at once (the pack)."""
        member = self.members(arch, width, depth, 1, steps)[0]
        reference, authors = copy.deepcopy(member.model), copy.deepcopy(member.model)
        _, reference_s = timed(lambda: reference_loop(reference, member, steps, self.train))
        _, authors_s = timed(lambda: authors_loop(authors, member, steps, self.train))
        (_, single), single_s = timed(lambda: train_lockstep([member], self.train))
        packed_members = self.members(arch, width, depth, pack, steps)
        (_, packed), packed_s = timed(lambda: train_lockstep(packed_members, self.train))
        return {"reference": reference_s / steps, "authors": authors_s / steps,
                "single": single_s / single[0][-1].outcome.steps, "packed": packed_s / packed[0][-1].outcome.steps,
                "params": parameter_count(member.model)}


def speed_table(bench: Bench, settings: BenchSettings) -> list[dict[str, Any]]:
    for arch in settings.archs:  # warm-up: the first passes through a code path pay one-off costs
        bench.step_seconds(arch, 2, 1, 16, 2)
    rows, pack = [], settings.pack_size
    for arch in settings.archs:
        for size, shape in settings.sizes.items():
            runs = [bench.step_seconds(arch, shape.width, shape.depth, settings.steps, pack)
                    for _ in range(settings.repeats)]  # interleaved; the fastest of each: the least disturbed
            seconds = {method: min(run[method] for run in runs) for method in runs[0]}
            rows.append({"arch": arch, "size": size, **dataclasses.asdict(shape), **seconds,
                         "single_ratio": seconds["reference"] / seconds["single"],
                         "packed_ratio": seconds["reference"] * pack / seconds["packed"],
                         "authors_single_ratio": seconds["authors"] / seconds["single"],
                         "authors_packed_ratio": seconds["authors"] * pack / seconds["packed"]})
    return rows


def task_breakdown(bench: Bench, task: TypicalTask, root: Path) -> dict[str, float]:
    """Seconds spent by one typical ``task`` in each phase."""
    python = [sys.executable, "-c"]
    _, interpreter_s = timed(lambda: subprocess.run([*python, "pass"], check=True))
    _, imports_s = timed(lambda: subprocess.run([*python, TASK_IMPORTS], check=True))
    miss_cache = ArrayCache(root / "miss")
    (data, _), miss_s = timed(lambda: (build_training_set(bench.system, 1, task.n_traj, miss_cache),
                                       build_test_set(bench.system, miss_cache)))
    (_, test), hit_s = timed(lambda: (build_training_set(bench.system, 1, task.n_traj, miss_cache),
                                      build_test_set(bench.system, miss_cache)))
    model = bench.model(task.arch, task.width, task.depth, 0)
    member = Member(model, data, Scaling.fit(data, bench.train.rescale_targets), task.epochs, 0)
    (stack, _), train_s = timed(lambda: train_lockstep([member], bench.train))
    dtype = getattr(torch, bench.train.dtype)
    metrics, score_s = timed(lambda: normalized_errors(test.dx, predict_derivatives(stack, test, [member.scaling],
                                                                                     dtype)[0]))
    _, write_s = timed(lambda: write_row_atomically({"task_id": "bench", **metrics}, root / "row.parquet"))
    return {"interpreter": interpreter_s, "imports": imports_s - interpreter_s, "data (miss)": miss_s,
            "data (hit)": hit_s, "training": train_s, "scoring": score_s, "writing": write_s}


def projected_core_hours(bench: Bench, settings: BenchSettings, breakdown: Mapping[str, float]) -> dict[str, float]:
    """Core-hours of the input-state study: each reference loop (each task its own process: interpreter,
    imports, simulated data, its steps, scoring, writing) and ours (the launcher's lockstep groups of
    ``pack_size``: a step costs the step time of its widest member for the models still training, between the
    measured K = 1 and K = ``pack_size``; per task data from the cache, scoring and writing); ours with epoch
    milestones (shared draws); and the planner's prediction."""
    launch, manifest = study_manifest("input_state")
    grid, pack = settings.projection, settings.pack_size
    costs = {}
    for arch in sorted({task["arch"] for task in manifest}):
        measured: dict[str, dict[tuple[int, int], float]] = defaultdict(dict)
        for width in grid.widths:
            for depth in grid.depths:
                for method, seconds in bench.step_seconds(arch, width, depth, grid.steps, pack).items():
                    measured[method][width, depth] = seconds
        costs[arch] = measured
    step_cost = lambda arch, method, width, depth: interpolate(  # noqa: E731
        costs[arch][method], grid.widths, grid.depths, width, depth)
    per_task = breakdown["data (hit)"] + breakdown["scoring"] + breakdown["writing"]
    process = breakdown["interpreter"] + breakdown["imports"] + breakdown["data (miss)"] - breakdown["data (hit)"]

    def one_process_per_task(method: str) -> float:
        return len(manifest) * (process + per_task) + sum(
            task["steps"] * step_cost(task["arch"], method, task["width"], task["depth"]) for task in manifest)

    def ours(tasks: list[dict[str, Any]], settings: Grouping, mode: str) -> tuple[float, int]:
        """Seconds and lockstep groups of ``tasks`` trained our way with lockstep ``settings``, the groups
        compiled as ``compile=mode`` would (``with_compile``: the cost values of the bench's compiled part)."""
        seconds, groups = len(tasks) * per_task, lockstep_groups(tasks, settings)
        for group in groups:
            arch, width, depth = group[0]["arch"], max(t["width"] for t in group), group[0]["depth"]
            single, packed = step_cost(arch, "single", width, depth), step_cost(arch, "packed", width, depth)
            seconds += with_compile(arch, sum(
                steps * (single + (packed - single) * (models - 1) / max(1, pack - 1))
                for steps, models in training_segments(group, settings)), cost, mode)[0]
        return seconds, len(groups)

    launched = launch_settings(launch)
    cost, grouping = launched.cost, dataclasses.replace(launched.grouping, size=pack)
    faithful, groups = ours(manifest, grouping, grouping.compile)
    eager, _ = ours(manifest, grouping, "never")
    shared_launch, shared = study_manifest("input_state", "draws=shared_across_epochs", "train.schedule_epochs=16384")
    milestones, _ = ours(shared, dataclasses.replace(launch_settings(shared_launch).grouping, size=pack),
                         grouping.compile)
    return {"core_hours_reference": one_process_per_task("reference") / 3600,
            "core_hours_authors": one_process_per_task("authors") / 3600, "core_hours_ours": faithful / 3600,
            "core_hours_ours_eager": eager / 3600, "core_hours_milestones": milestones / 3600,
            "core_hours_planner": planner_core_hours(launch, manifest), "tasks": len(manifest), "groups": groups,
            "compile": grouping.compile}


def largest_task_peak_memory(largest_task: Sequence[str], root: Path) -> float:
    """Peak resident memory (GiB) of `python -m nsl_hpc.train` on the largest input-state task (``largest_task``:
    its key=value arguments)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    subprocess.run([sys.executable, "-m", "nsl_hpc.train", *largest_task, f"out_dir={root / 'largest'}",
                    f"cache_dir={root / 'largest-cache'}"], check=True, capture_output=True)
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(peak_kib, before) / 2**20


def report(speeds: list[dict], breakdown: Mapping[str, float], peak: float, projection: Mapping[str, float],
           memory_gib: float, settings: BenchSettings) -> str:
    """The figures as markdown (docs/performance.md's table)."""
    batch, pack = settings.train.batch_size, settings.pack_size
    lines = [f"Measured by `python -m nsl_hpc.bench` on one core ({torch.get_num_threads()} thread), "
             f"{settings.steps} steps of batch {batch} on {settings.system.name} (the fastest of {settings.repeats} "
             f"interleaved runs), K = {pack} packed models.", "",
             "| arch | n_h | n_d | p | plain loop samples/s | authors' loop | ours alone | ratio (authors') | "
             "ours packed, per model | ratio (authors') | GFLOP/s packed (% of peak) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in speeds:
        packed_rate = batch * pack / row["packed"]
        flops = 6 * row["params"] * packed_rate
        share = 100 * flops / peak
        lines.append(f"| {row['arch']} | {row['width']} | {row['depth']} | {row['params']:,} | "
                     f"{batch / row['reference']:,.0f} | {batch / row['authors']:,.0f} | "
                     f"{batch / row['single']:,.0f} | "
                     f"{row['single_ratio']:.2f}x ({row['authors_single_ratio']:.1f}x) | {packed_rate:,.0f} | "
                     f"{row['packed_ratio']:.1f}x ({row['authors_packed_ratio']:.0f}x) | "
                     f"{flops / 1e9:.2f} ({share:.1f}%) |")
    lines += ["", f"Dense float32 matmul peak of this core: {peak / 1e9:.1f} GFLOP/s.", "",
              "| one task (" + ", ".join(f"{k}={v}" for k, v in dataclasses.asdict(settings.typical_task).items())
              + ") | seconds |",
              "|---|---:|"]
    lines += [f"| {phase} | {seconds:.3f} |" for phase, seconds in breakdown.items()]
    reference, ours = projection["core_hours_reference"], projection["core_hours_ours"]
    lines += ["", f"Projected core-hours of the {projection['tasks']:,}-task input-state study, one process per task: "
              f"plain loop {reference:,.0f}, authors' loop {projection['core_hours_authors']:,.0f}; ours "
              f"{ours:,.0f} ({reference / ours:.1f}x fewer than the plain loop, "
              f"{projection['core_hours_authors'] / ours:.1f}x fewer than the authors'; {projection['groups']:,} "
              f"lockstep groups of up to K = {pack}; compile={projection['compile']}: the groups the planner "
              "compiles at `cost.compile_speedup` and `cost.compile_s`, nsl_hpc.bench parts=[compiled]; eager "
              f"{projection['core_hours_ours_eager']:,.0f}). With epoch milestones (shared draws, "
              "train.schedule_epochs = the largest epoch count; rows of another meaning, see Epoch milestones) "
              f"{projection['core_hours_milestones']:,.0f} ({reference / projection['core_hours_milestones']:.1f}x "
              f"fewer). The planner predicts {projection['core_hours_planner']:,.0f} (`cost.*`, for time limits).",
              f"Peak memory of the largest input-state task: {memory_gib:.2f} GiB."]
    return "\n".join(lines)


def input_state_part(settings: BenchSettings, root: Path) -> tuple[str, dict[str, Any]]:
    """The input-state table (docs/performance.md) and its headline figures."""
    bench = Bench(settings, ArrayCache(root / "cache"))
    speeds = speed_table(bench, settings)
    peak = matmul_peak_flops(settings.matmul_size)
    breakdown = task_breakdown(bench, settings.typical_task, root)
    projection = projected_core_hours(bench, settings, breakdown)
    memory = largest_task_peak_memory(settings.largest_task, root)
    headline = {"single_speedup_min": min(row["single_ratio"] for row in speeds),
                "packed_speedup": min(row["packed_ratio"] for row in speeds),
                "authors_single_speedup_min": min(row["authors_single_ratio"] for row in speeds),
                "authors_packed_speedup": min(row["authors_packed_ratio"] for row in speeds),
                **{k: v for k, v in projection.items() if k.startswith("core_hours")},
                "largest_task_peak_gib": memory, "matmul_peak_gflops": peak / 1e9, "speeds": speeds,
                "task_seconds": breakdown}
    return report(speeds, breakdown, peak, projection, memory, settings), headline
