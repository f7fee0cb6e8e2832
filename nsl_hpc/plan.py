"""Planning a sweep's jobs: predicted task times, lockstep groups of same-shape tasks, packs of short
groups, time classes, and SLURM limits."""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from nsl_hpc.errors import ConfigError


def predicted_seconds(arch: str, steps: int, params: int, cost: Mapping[str, Any]) -> float:
    """Predicted wall time (s) of one task on one core, from the ``cost`` config (a plain dict when
    called per task of a large sweep: DictConfig lookups are slow)."""
    per_step = cost["step_seconds"][arch] * (1 + params / cost["params_per_overhead"])
    return cost["startup_s"] + steps * per_step


SHAPE_KEYS = ("system", "arch", "width", "depth")  # tasks that agree on these can train in lockstep


def lockstep_groups(tasks: Sequence[Mapping[str, Any]], size: int) -> list[list[Mapping[str, Any]]]:
    """Manifest rows in groups of at most ``size`` tasks of one shape (SHAPE_KEYS) that train in lockstep,
    by step count so that a group's members run about equally long; size 1 trains every task alone."""
    by_shape: dict[tuple, list[Mapping[str, Any]]] = {}
    for task in tasks:
        by_shape.setdefault(tuple(task[key] for key in SHAPE_KEYS), []).append(task)
    groups = []
    for shape in sorted(by_shape, key=str):
        members = sorted(by_shape[shape], key=lambda task: (task["steps"], task["task_id"]))
        groups += [members[start:start + size] for start in range(0, len(members), size)]
    return groups


def group_seconds(group: Sequence[Mapping[str, Any]], cost: Mapping[str, Any]) -> float:
    """Predicted wall time (s) of a lockstep group: its longest member, each further member adding
    ``cost.lockstep_extra`` of a step."""
    longest = max(group, key=lambda task: task["steps"])
    alone = predicted_seconds(longest["arch"], longest["steps"], longest["params"], cost)
    return cost["startup_s"] + (alone - cost["startup_s"]) * (1 + (len(group) - 1) * cost["lockstep_extra"])


def planned_groups(tasks: Sequence[Mapping[str, Any]], size: int, cost: Mapping[str, Any]
                   ) -> tuple[list[tuple[str, ...]], list[float]]:
    """The lockstep groups of ``tasks`` as task-id tuples, and their predicted seconds (``make_packs``'s input)."""
    groups = lockstep_groups(tasks, size)
    return ([tuple(task["task_id"] for task in group) for group in groups],
            [group_seconds(group, cost) for group in groups])


@dataclass(frozen=True)
class Pack:
    """Tasks that run one after another in one job; ``seconds`` is their predicted total."""

    task_ids: tuple[str, ...]
    seconds: float
    time_limit_min: int


def time_limit_minutes(seconds: float, packing: Mapping[str, Any]) -> int:
    """The smallest time class that holds ``time_safety`` times the predicted ``seconds``."""
    needed = seconds * packing["time_safety"] / 60
    for limit in packing["time_classes_minutes"]:
        if needed <= limit:
            return int(limit)
    raise ConfigError(f"a job predicted at {seconds / 3600:.1f} h needs {needed / 60:.1f} h with time_safety="
                      f"{packing['time_safety']}, more than the largest of packing.time_classes_minutes="
                      f"{list(packing['time_classes_minutes'])}; add a larger class or lower the safety factor")


def lockstep_size(launch: Mapping[str, Any]) -> int:
    """K, the models a job trains in lockstep: ``lockstep.size`` when enabled and the study can, else 1."""
    from nsl_hpc.studies import study_named

    enabled = launch["lockstep"]["enabled"] and study_named(launch["study"]["name"]).lockstep
    return int(launch["lockstep"]["size"]) if enabled else 1


def packing_for(packing: Mapping[str, Any], launcher_name: str, time_factor: float = 1.0) -> dict[str, Any]:
    """The packing settings a launcher uses: packing is for the scheduler (local workers balance single
    tasks), and ``time_factor`` stretches the time limits (resubmission after timeouts)."""
    return {**packing, "enabled": packing["enabled"] and launcher_name == "slurm",
            "time_safety": packing["time_safety"] * time_factor}


def make_packs(groups: Sequence[tuple[str, ...]], seconds: Sequence[float], packing: Mapping[str, Any]) -> list[Pack]:
    """Put lockstep groups (task-id tuples, ``planned_groups``) into packs that run one after another in a
    job: short groups (under ``short_task_minutes``) fill packs of about ``pack_minutes`` of predicted
    work; longer ones (or all, with packing disabled) run alone."""
    order = np.argsort(seconds, kind="stable")
    short_limit = packing["short_task_minutes"] * 60 if packing["enabled"] else 0.0
    packs, current, total = [], [], 0.0
    for index in order:
        group, cost = groups[index], float(seconds[index])
        if cost >= short_limit:
            packs.append(Pack(tuple(group), cost, time_limit_minutes(cost, packing)))
            continue
        if current and total + cost > packing["pack_minutes"] * 60:
            packs.append(Pack(tuple(current), total, time_limit_minutes(total, packing)))
            current, total = [], 0.0
        current.extend(group)
        total += cost
    if current:
        packs.append(Pack(tuple(current), total, time_limit_minutes(total, packing)))
    return packs
