"""Planning a sweep's jobs: predicted task times, packs of short tasks, time classes, and SLURM limits."""

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


def packing_for(packing: Mapping[str, Any], launcher_name: str, time_factor: float = 1.0) -> dict[str, Any]:
    """The packing settings a launcher uses: packing is for the scheduler (local workers balance single
    tasks), and ``time_factor`` stretches the time limits (resubmission after timeouts)."""
    return {**packing, "enabled": packing["enabled"] and launcher_name == "slurm",
            "time_safety": packing["time_safety"] * time_factor}


def make_packs(task_ids: Sequence[str], seconds: Sequence[float], packing: Mapping[str, Any]) -> list[Pack]:
    """Group tasks into packs: short tasks (under ``short_task_minutes``) fill packs of about
    ``pack_minutes`` of predicted work; longer ones (or all, with packing disabled) run alone."""
    order = np.argsort(seconds, kind="stable")
    short_limit = packing["short_task_minutes"] * 60 if packing["enabled"] else 0.0
    packs, current, total = [], [], 0.0
    for index in order:
        task, cost = task_ids[index], float(seconds[index])
        if cost >= short_limit:
            packs.append(Pack((task,), cost, time_limit_minutes(cost, packing)))
            continue
        if current and total + cost > packing["pack_minutes"] * 60:
            packs.append(Pack(tuple(current), total, time_limit_minutes(total, packing)))
            current, total = [], 0.0
        current.append(task)
        total += cost
    if current:
        packs.append(Pack(tuple(current), total, time_limit_minutes(total, packing)))
    return packs
