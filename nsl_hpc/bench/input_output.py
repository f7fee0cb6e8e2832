"""The input-output rows of ``python -m nsl_hpc.bench``: the plain per-model loop against ours, alone and packed.

1. per architecture at a small and a large size: seconds per iteration of the reference (``train_io_model``,
   the plain loop a user writes: a random batch of windows, forward or T-step rollout, MSE, backward,
   clip_grad_norm_, Adam, the warm-up + cosine schedule), of ours alone (``train_lockstep``, K = 1) and per model
   of ours packed (K models as the planner groups them: ``lockstep.size`` within ``lockstep.memory_mb``);
2. scoring: seconds per model and test sample, alone and in a pack (free run, and NARX one step ahead);
3. the projected core-hours of the 42,120-task input-output study, each task its own process with the
   reference loop against the planner's packed groups with ours, from per-iteration costs measured on a
   (n_h, n_d) grid (SUBNET's scaled by each system's T over the stand-in's); and the planner's own prediction
   (``cost.*``), with the cost values that a least-squares fit of these measurements gives it.
Everything on the simulated Silverbox stand-in (``io.system``), one thread.
"""

import copy
import dataclasses
import math
import subprocess
import sys
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nsl_hpc.bench.measure import TASK_IMPORTS, interpolate, planner_core_hours, study_manifest, timed
from nsl_hpc.bench.settings import BenchSettings, IoBench
from nsl_hpc.config import compose_config, plain
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_output.data import load_benchmark
from nsl_hpc.studies.input_output.lockstep import IOMember, train_lockstep
from nsl_hpc.studies.input_output.scoring import numpy_mlps, score_records
from nsl_hpc.studies.input_output.study import InputOutput, build_io_model, horizon, training_memory_mb
from nsl_hpc.studies.input_output.training import SignalScaling, train_io_model
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.plan import lockstep_groups, training_segments, with_compile


class IOBench:
    """Models and data of the input-output benchmark, built once."""

    def __init__(self, io: IoBench, cache: ArrayCache):
        self.io = io
        self.launch = launch_settings(compose_config(["+sweep=input_output", f"data_dir={io.data_dir}"], "launch"))
        self.bases = {arch: InputOutput().pair(plain(compose_config(
            ["study=input_output", f"system={self.io.system}", f"arch={arch}"], "one_task"))) for arch in self.io.archs}
        self.benchmark = load_benchmark(self.bases[self.io.archs[0]].system, cache)
        self.record = self.benchmark.train.head(self.io.train_points)

    def pack_size(self, arch: str, width: int, depth: int) -> int:
        """K of a group of this size as the planner makes it: lockstep.size within lockstep.memory_mb."""
        lockstep = self.launch.lockstep
        return max(1, min(lockstep.size, math.floor(lockstep.memory_mb / training_memory_mb(self.bases[arch], width,
                                                                                                depth))))

    def members(self, arch: str, width: int, depth: int, count: int, iterations: int) -> list[IOMember]:
        base, scaling = self.bases[arch], SignalScaling.fit(self.record)
        members = []
        for k in range(count):
            torch.manual_seed(k)
            members.append(IOMember(build_io_model(base.arch, base.system, width, depth), self.record, scaling,
                                    iterations, k, horizon(base)))
        return members

    def iteration_seconds(self, arch: str, width: int, depth: int, iterations: int) -> dict[str, float]:
        """Seconds per iteration: the reference loop, ours alone, ours for a pack (all its models), and K."""
        base = self.bases[arch]
        member = self.members(arch, width, depth, 1, iterations)[0]
        reference = copy.deepcopy(member.model)
        steps = horizon(base)
        _, reference_s = timed(lambda: train_io_model(reference, member.record, member.scaling, base.train,
                                                      iterations, steps, 0))
        _, single_s = timed(lambda: train_lockstep([member], base.train))
        pack = self.pack_size(arch, width, depth)
        packed = self.members(arch, width, depth, pack, iterations)
        _, packed_s = timed(lambda: train_lockstep(packed, base.train))
        return {"reference": reference_s / iterations, "single": single_s / iterations,
                "packed": packed_s / iterations, "pack": pack, "params": member.model.counted_parameters()}

    def scoring_seconds(self, arch: str, pack: int) -> dict[str, float]:
        """Seconds per model and test sample of scoring (n_h 8, n_d 2), alone and in a pack of ``pack``."""
        base = self.bases[arch]
        test = {"test": self.benchmark.tests[base.system.score_on]}
        seconds = {}
        for name, count in (("alone", 1), ("packed", pack)):
            members = self.members(arch, 8, 2, count, 0)
            nets, theta, _ = train_lockstep(members, base.train)
            _, elapsed = timed(lambda: score_records(members[0].model, numpy_mlps(nets, theta),  # noqa: B023
                                                     [m.scaling for m in members], test,  # noqa: B023
                                                     base.system.init_samples, 1.0))
            seconds[name] = elapsed / count / len(test["test"])
        return seconds


def speed_rows(bench: IOBench) -> list[dict[str, Any]]:
    io = bench.io
    for arch in io.archs:  # warm-up: the first passes through a code path pay one-off costs
        bench.iteration_seconds(arch, 2, 1, 4)
    rows = []
    for arch in io.archs:
        for size, shape in io.sizes[arch].items():
            runs = [bench.iteration_seconds(arch, shape.width, shape.depth, io.iterations[arch])
                    for _ in range(io.repeats)]
            seconds = {key: min(run[key] for run in runs) for key in runs[0]}
            rows.append({"arch": arch, "size": size, **dataclasses.asdict(shape), **seconds,
                         "single_ratio": seconds["reference"] / seconds["single"],
                         "packed_ratio": seconds["reference"] * seconds["pack"] / seconds["packed"]})
    return rows


def study_systems(data_dir: str, cache_dir: str, systems: set[str]) -> dict[str, tuple[int, int]]:
    """Per system of the study (its records in ``data_dir``, read through the cache in ``cache_dir``): the samples
    scored per model (all its test records) and SUBNET's T."""
    facts = {}
    for system in sorted(systems):
        pair = pair_of(compose_config([f"data_dir={data_dir}", "study=input_output", f"system={system}"], "one_task"))
        settings = pair.system
        records = load_benchmark(settings, ArrayCache(cache_dir)).tests.values()
        facts[system] = sum(len(record) for record in records), settings.subnet.horizon
    return facts


def projection(bench: IOBench, process_s: float) -> dict[str, Any]:
    """Core-hours of the input-output study: one process per task with the reference loop (``process_s``:
    interpreter and imports) against the planner's groups with ours, and the planner's own prediction, with
    the cost values fitted to the measurements."""
    io, grid = bench.io, bench.io.projection
    launch, manifest = study_manifest("input_output", f"data_dir={io.data_dir}")
    measured: dict[str, dict] = {}
    for arch in io.archs:
        table: dict[str, dict[tuple[int, int], float]] = defaultdict(dict)
        for width in grid.widths[arch]:
            for depth in grid.depths:
                for key, value in bench.iteration_seconds(arch, width, depth, grid.iterations[arch]).items():
                    table[key][width, depth] = value
        measured[arch] = table
    launched = launch_settings(launch)
    scoring = {arch: bench.scoring_seconds(arch, launched.lockstep.size) for arch in io.archs}
    systems = study_systems(io.data_dir, launch.cache_dir, {task["system"] for task in manifest})
    samples = {system: facts[0] for system, facts in systems.items()}
    stand_in_horizon = horizon(bench.bases["subnet"]) if "subnet" in bench.bases else 1

    def cost(task: Mapping[str, Any], key: str, width: int | None = None) -> float:
        arch = task["arch"]
        table = measured[arch][key]
        value = interpolate(table, grid.widths[arch], grid.depths, width or task["width"], task["depth"])
        return value * systems[task["system"]][1] / stand_in_horizon if arch == "subnet" else value

    reference = sum(process_s + task["steps"] * cost(task, "reference")
                    + samples[task["system"]] * scoring[task["arch"]]["alone"] for task in manifest)
    settings, cost_values = launched.grouping, launched.cost
    groups = lockstep_groups(manifest, settings)
    ours = eager = len(groups) * process_s
    for group in groups:
        first, width = group[0], max(task["width"] for task in group)
        single, packed = cost(first, "single", width), cost(first, "packed", width)
        pack = interpolate(measured[first["arch"]]["pack"], grid.widths[first["arch"]], grid.depths, width,
                           first["depth"])
        per_model = (packed - single) / max(1.0, pack - 1)
        training = sum(steps * (single + per_model * (models - 1))
                       for steps, models in training_segments(group, settings))
        scored = sum(samples[task["system"]] * scoring[task["arch"]]["packed"] for task in group)
        ours += with_compile(first["arch"], training, cost_values, settings.compile)[0] + scored
        eager += training + scored
    try:
        planner: float | str = planner_core_hours(launch, manifest)
    except ConfigError as error:  # e.g. cost values under which a group outgrows every time class
        planner = f"refused: {error}"
    return {"io_core_hours_reference": reference / 3600, "io_core_hours_ours": ours / 3600,
            "io_core_hours_ours_eager": eager / 3600, "io_compile": settings.compile,
            "io_core_hours_planner": planner, "io_tasks": len(manifest),
            "io_groups": len(groups), "io_calibrated_cost": calibrated_cost(measured),
            "io_scoring_seconds_per_sample": scoring}


def calibrated_cost(measured: Mapping[str, Mapping[str, Mapping[tuple[int, int], float]]]) -> dict[str, dict]:
    """``cost.*`` values for the planner fitted to the measurements, per architecture: seconds per step alone
    a + b p by least squares on the relative error (step_seconds = a, params_per_overhead = a / b), and
    lockstep_extra the median of (pack time / alone time - 1) / (K - 1)."""
    fitted: dict[str, dict] = {"step_seconds": {}, "params_per_overhead": {}, "lockstep_extra": {}}
    for arch, table in measured.items():
        points = sorted(table["single"])
        seconds = np.array([table["single"][point] for point in points])
        params = np.array([table["params"][point] for point in points])
        design = np.stack([np.ones_like(params), params], axis=1) / seconds[:, None]
        (a, b), *_ = np.linalg.lstsq(design, np.ones_like(seconds), rcond=None)
        extras = [(table["packed"][point] / table["single"][point] - 1) / (table["pack"][point] - 1)
                  for point in points if table["pack"][point] > 1]
        fitted["step_seconds"][arch] = float(a)
        fitted["params_per_overhead"][arch] = float(a / b) if b > 0 else math.inf
        fitted["lockstep_extra"][arch] = float(np.median(extras)) if extras else 0.0
    return fitted


def report(rows: list[dict[str, Any]], projected: Mapping[str, Any], io: IoBench) -> str:
    """The input-output figures as markdown."""
    lines = [f"Input-output study, on {io.system} (the fastest of {io.repeats} runs; {io.train_points:,}-sample "
             "prefix, batch 256):", "",
             "| arch | n_h | n_d | p | plain loop s/it | ours alone | ratio | K packed | ours packed, per model | "
             "ratio |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['arch']} | {row['width']} | {row['depth']} | {row['params']:,} | "
                     f"{row['reference']:.4f} | {row['single']:.4f} | {row['single_ratio']:.2f}x | {row['pack']} | "
                     f"{row['packed'] / row['pack']:.4f} | {row['packed_ratio']:.1f}x |")
    reference, ours = projected["io_core_hours_reference"], projected["io_core_hours_ours"]
    planner = projected["io_core_hours_planner"]
    fitted = projected["io_calibrated_cost"]
    lines += ["", f"Projected core-hours of the {projected['io_tasks']:,}-task input-output study: plain loop, one "
              f"process per task, {reference:,.0f}; ours {ours:,.0f} ({reference / ours:.1f}x fewer; "
              f"{projected['io_groups']:,} packed groups; compile={projected['io_compile']}, at `cost.compile_speedup` "
              f"and `cost.compile_s`; eager {projected['io_core_hours_ours_eager']:,.0f}). The planner predicts "
              f"{planner if isinstance(planner, str) else f'{planner:,.0f}'} "
              "(`cost.*`). Fitted cost values: " + "; ".join(
                  f"{arch}: step_seconds {fitted['step_seconds'][arch]:.3g}, params_per_overhead "
                  f"{fitted['params_per_overhead'][arch]:.3g}, lockstep_extra {fitted['lockstep_extra'][arch]:.3g}"
                  for arch in fitted["step_seconds"]) + "."]
    return "\n".join(lines)


def input_output_part(settings: BenchSettings, root: Path) -> tuple[str, dict[str, Any]]:
    """The input-output table and its headline figures."""
    python = [sys.executable, "-c"]
    _, process_s = timed(lambda: subprocess.run([*python, TASK_IMPORTS], check=True))
    bench = IOBench(settings.io, ArrayCache(root / "io-cache"))
    rows = speed_rows(bench)
    projected = projection(bench, process_s)
    headline = {"io_single_speedup_min": min(row["single_ratio"] for row in rows),
                "io_packed_speedup": min(row["packed_ratio"] for row in rows), **projected, "io_speeds": rows}
    return report(rows, projected, settings.io), headline
