"""Planning a sweep's jobs: predicted task times, lockstep groups of same-shape tasks, packs of short
groups, time classes, and SLURM limits."""

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.launchers import Launcher, SlurmLauncher
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies.base import model_of
from nsl_hpc.sweep.run_settings import Cost, Packing


@dataclass(frozen=True)
class Grouping:
    """How the planner groups a sweep's tasks: ``size`` (K, the models a group trains in lockstep: ``lockstep.size``
    when enabled and the study can, else 1), ``width_buckets`` and ``memory_mb`` (``lockstep``), ``model_keys`` (the
    keys of one model: with epoch milestones the study's draw keys, else none: a model per task) and ``compile``."""

    size: int
    width_buckets: tuple[int, ...]
    memory_mb: float
    model_keys: tuple[str, ...]
    compile: str


@dataclass(frozen=True)
class JobPacking:
    """The packing a launcher's jobs get (``packing_for``): packing only for the scheduler, ``time_safety``
    stretched by a resubmission's factor, the time classes within the site's cap ``max_time_minutes`` (None:
    none)."""

    enabled: bool
    short_task_minutes: float
    pack_minutes: float
    time_safety: float
    time_classes_minutes: tuple[float, ...]
    max_time_minutes: int | None = None


def predicted_seconds(arch: str, steps: int, params: int, cost: Cost) -> float:
    """Predicted wall time (s) of one task on one core, from the ``cost`` settings."""
    per_step = cost.step_seconds[arch] * (1 + params / cost.params_per_overhead[arch])
    return cost.startup_s + steps * per_step


def padded_width(width: int, buckets: Sequence[int]) -> int:
    """The width a task trains at in a lockstep group: the smallest of ``buckets`` that holds it (its own
    width when none does)."""
    return min((bucket for bucket in buckets if bucket >= width), default=width)


def lockstep_key(task: Mapping[str, Any], buckets: Sequence[int]) -> tuple:
    """Tasks with equal keys can train in lockstep: one system, architecture and depth, widths in one bucket; a
    model the lockstep training cannot batch (``stackable`` false: a user's torch.nn.Module) has a key of its own."""
    alone = () if task.get("stackable", True) else (task["task_id"],)
    return task["system"], task["arch"], task["depth"], padded_width(task["width"], buckets), *alone


def lockstep_groups(tasks: Sequence[Mapping[str, Any]], lockstep: Grouping) -> list[list[Mapping[str, Any]]]:
    """Manifest rows in groups of the tasks of at most ``lockstep.size`` models (``model_of``) of one
    ``lockstep_key`` that train in lockstep, by step count so that a group's models run about equally long, and
    so that their number times the largest's ``train_memory_mb`` stays within ``lockstep.memory_mb`` (a
    model alone may exceed it); size 1 trains every model alone. Groups fill from the longest models down, so
    the one left short holds the shortest: a key's groups then take the fewest steps in all (the input-state
    study's 17% fewer than filling from the shortest up), and much of a step's cost does not depend on how
    many models it carries. Each group, and a key's groups, in ascending step order."""
    runs: dict[tuple, list[Mapping[str, Any]]] = {}
    for task in tasks:
        runs.setdefault(model_of(task, lockstep.model_keys), []).append(task)
    by_key: dict[tuple, list[list[Mapping[str, Any]]]] = {}
    for run in runs.values():
        by_key.setdefault(lockstep_key(run[0], lockstep.width_buckets), []).append(run)
    groups = []
    for key in sorted(by_key, key=str):
        members = sorted(by_key[key], key=lambda run: (max(task["steps"] for task in run), run[0]["task_id"]),
                         reverse=True)
        key_groups: list[list[list[Mapping[str, Any]]]] = [[]]
        largest = 0.0  # the largest train_memory_mb of the group being filled
        for run in members:
            group, largest = key_groups[-1], max(largest, memory_mb(run))
            if group and (len(group) == lockstep.size or (len(group) + 1) * largest > lockstep.memory_mb):
                key_groups.append(group := [])
                largest = memory_mb(run)
            group.append(run)
        groups += [[task for member in reversed(group) for task in member] for group in reversed(key_groups)]
    return groups


def memory_mb(run: Sequence[Mapping[str, Any]]) -> float:
    """The training memory (MB) of a model (its tasks' ``train_memory_mb``; 0 when the study has none)."""
    return max(task.get("train_memory_mb", 0.0) for task in run)


def model_steps(group: Sequence[Mapping[str, Any]], lockstep: Grouping) -> list[int]:
    """The steps each model of a lockstep group trains (its longest task's), ascending."""
    steps: dict[tuple, int] = {}
    for task in group:
        key = model_of(task, lockstep.model_keys)
        steps[key] = max(steps.get(key, 0), task["steps"])
    return sorted(steps.values())


def training_segments(group: Sequence[Mapping[str, Any]], lockstep: Grouping) -> list[tuple[int, int]]:
    """(steps, models training) of a lockstep group, segment by segment: models that finish leave."""
    steps = model_steps(group, lockstep)
    return [(stop - start, len(steps) - index)
            for index, (start, stop) in enumerate(zip([0, *steps[:-1]], steps, strict=True))]


def training_seconds(group: Sequence[Mapping[str, Any]], cost: Cost, lockstep: Grouping) -> float:
    """Predicted eager seconds of a lockstep group's training steps: a step of its largest member costs what it
    costs alone, plus ``cost.lockstep_extra[arch]`` of that for each further model still training (finished ones
    leave)."""
    largest = max(group, key=lambda task: task["params"])
    per_step = predicted_seconds(largest["arch"], 1, largest["params"], cost) - cost.startup_s
    extra = cost.lockstep_extra[largest["arch"]]
    return sum(steps * per_step * (1 + (models - 1) * extra) for steps, models in training_segments(group, lockstep))


def fixed_seconds(group: Sequence[Mapping[str, Any]], cost: Cost) -> float:
    """Predicted seconds of a lockstep group's own start in its job (``cost.group_start_s``) and of scoring each
    task, ``cost.score_seconds`` per test sample and parameter (its ``test_points``: none for the input-output
    study, whose manifest has no such column)."""
    return cost.group_start_s + cost.score_seconds * sum(
        task.get("test_points", 0) * task["params"] for task in group)


def compiles(arch: str, eager_seconds: float, cost: Cost, mode: str) -> bool:
    """Whether a lockstep group of ``arch`` predicted at ``eager_seconds`` compiles its step (``compile``: always,
    never, or auto: when the predicted saving, eager_seconds (1 - 1 / cost.compile_speedup[arch]), exceeds what
    compiling costs, cost.compile_s[arch]; an architecture whose compile_speedup is null runs eagerly)."""
    if mode != "auto":
        return mode == "always"
    speedup = cost.compile_speedup.get(arch)
    return speedup is not None and eager_seconds * (1 - 1 / speedup) > (cost.compile_s[arch] or 0.0)


def with_compile(arch: str, eager_seconds: float, cost: Cost, mode: str) -> tuple[float, bool]:
    """A group's predicted seconds and whether it compiles (``compiles``): compiled, its eager seconds over
    cost.compile_speedup[arch] (1 when null) plus cost.compile_s[arch] (0 when null)."""
    if not compiles(arch, eager_seconds, cost, mode):
        return eager_seconds, False
    speedup = cost.compile_speedup.get(arch) or 1.0
    return eager_seconds / speedup + (cost.compile_s.get(arch) or 0.0), True


@dataclass(frozen=True)
class Group:
    """Tasks one process trains together (in lockstep; one task when K = 1); ``seconds``: predicted wall time;
    ``compiled``: whether its training step is compiled (``compiles``)."""

    task_ids: tuple[str, ...]
    seconds: float
    compiled: bool = False


def planned_group(group: Sequence[Mapping[str, Any]], cost: Cost, lockstep: Grouping) -> Group:
    """The ``Group`` of a lockstep group's tasks: its predicted seconds, its training compiled where that pays
    (``compiles`` on the training seconds alone: start-up and scoring are the same either way)."""
    training, compiled = with_compile(group[0]["arch"], training_seconds(group, cost, lockstep), cost,
                                      lockstep.compile)
    return Group(tuple(task["task_id"] for task in group), fixed_seconds(group, cost) + training, compiled)


@dataclass(frozen=True)
class Pack:
    """Lockstep groups that run one after another in one job; ``seconds`` is their predicted total. The job
    trains exactly these groups (``nsl_hpc.sweep.job``)."""

    groups: tuple[Group, ...]
    seconds: float
    time_limit_min: int
    chain: int = 1  # jobs it runs as: more than one when longer than launcher.max_time_minutes (requeued)

    @property
    def task_ids(self) -> tuple[str, ...]:
        return tuple(task_id for group in self.groups for task_id in group.task_ids)

    def task_seconds(self) -> list[float]:
        """Each task's predicted seconds (``task_ids`` order): its share of its group's, and of what the pack's
        prediction holds beyond its groups' (the job's start)."""
        start = (self.seconds - sum(group.seconds for group in self.groups)) / len(self.task_ids)
        return [group.seconds / len(group.task_ids) + start for group in self.groups for _ in group.task_ids]


def planned_groups(tasks: Sequence[Mapping[str, Any]], lockstep: Grouping, cost: Cost,
                   longest_s: float = math.inf) -> list[Group]:
    """The lockstep groups of ``tasks`` with their predicted seconds (``make_packs``'s input); a group predicted
    longer than ``longest_s`` is halved (by model, in its order) until each part fits or holds one model."""
    def fitting(group: list[Mapping[str, Any]]) -> list[Group]:
        planned = planned_group(group, cost, lockstep)
        models = list(dict.fromkeys(model_of(task, lockstep.model_keys) for task in group))
        if planned.seconds <= longest_s or len(models) == 1:
            return [planned]
        first = set(models[:len(models) // 2])
        return [part for half in (True, False) for part in fitting(
            [task for task in group if (model_of(task, lockstep.model_keys) in first) == half])]

    return [part for group in lockstep_groups(tasks, lockstep) for part in fitting(group)]


def job_time(seconds: float, packing: JobPacking) -> tuple[int, int]:
    """(time limit in minutes, jobs in its chain) of a job predicted at ``seconds``: the smallest time class that
    holds ``time_safety`` times that, or, beyond the largest with a site cap (``max_time_minutes``), that cap and
    as many jobs as hold it, each continuing from the last one's checkpoint."""
    needed = seconds * packing.time_safety / 60
    for limit in packing.time_classes_minutes:
        if needed <= limit:
            return int(limit), 1
    cap = packing.max_time_minutes
    if cap:
        return int(cap), math.ceil(needed / cap)
    raise ConfigError(f"a job predicted at {seconds / 3600:.1f} h needs {needed / 60:.1f} h with time_safety="
                      f"{packing.time_safety}, more than the largest of packing.time_classes_minutes="
                      f"{list(packing.time_classes_minutes)}; add a larger class or lower the safety factor")


def check_signal_delay(signal_delay_s: int, time_classes_minutes: Sequence[float]) -> None:
    """Raise ConfigError unless SLURM's warning (``--signal``, sent up to 30 s early: slurmctld checks time
    limits every 30 s) reaches every job after its start-up, i.e. leaves at least 5 s of its shortest limit."""
    shortest_s = 60 * min(time_classes_minutes)
    if signal_delay_s + 30 > shortest_s - 5:
        raise ConfigError(f"launcher.signal_delay_s={signal_delay_s} leaves no start-up time in a "
                          f"{shortest_s / 60:g}-minute job (SLURM may warn up to 30 s early): use at most "
                          f"{max(int(shortest_s) - 35, 0)} or a longer packing.time_classes_minutes")


def packing_for(packing: Packing, launcher: Launcher, time_factor: float = 1.0) -> JobPacking:
    """The packing a launcher's jobs get: packing is for the scheduler (local workers balance single tasks),
    ``time_factor`` stretches the time limits (resubmission after timeouts), and a site cap
    (``launcher.max_time_minutes``) bounds the time classes."""
    cap = launcher.max_time_minutes if isinstance(launcher, SlurmLauncher) else None
    classes = list(packing.time_classes_minutes)
    if cap:
        classes = [limit for limit in classes if limit < cap] + [cap]
    return JobPacking(packing.enabled and isinstance(launcher, SlurmLauncher), packing.short_task_minutes,
                      packing.pack_minutes, packing.time_safety * time_factor, tuple(classes), cap)


def make_packs(groups: Sequence[Group], packing: JobPacking, startup_s: float = 0.0) -> list[Pack]:
    """Put lockstep groups (``planned_groups``) into packs that run one after another in a job: short groups
    (under ``short_task_minutes``) fill packs of about ``pack_minutes`` of predicted work; longer ones (or
    all, with packing disabled) run alone. A pack's seconds are its groups' plus the job's ``startup_s``."""
    short_limit = packing.short_task_minutes * 60 if packing.enabled else 0.0
    packs: list[Pack] = []
    current: list[Group] = []
    total = 0.0

    def close(members: list[Group], seconds: float) -> None:
        packs.append(Pack(tuple(members), startup_s + seconds, *job_time(startup_s + seconds, packing)))

    for group in sorted(groups, key=lambda group: group.seconds):  # stable: equal times keep their order
        if group.seconds >= short_limit:
            close([group], group.seconds)
            continue
        if current and total + group.seconds > packing.pack_minutes * 60:
            close(current, total)
            current, total = [], 0.0
        current.append(group)
        total += group.seconds
    if current:
        close(current, total)
    return packs


def plan_jobs(tasks: Sequence[Mapping[str, Any]], grouping: Grouping, cost: Cost, packing: JobPacking,
              startup_s: float, saved: Sequence[Sequence[str]] = ()) -> list[Pack]:
    """The jobs that run ``tasks`` (manifest rows): lockstep groups (``sweep_groups``) with predicted times, packed
    for the launcher (``packing``), each job starting in ``startup_s``. ``saved``: the task ids (training order)
    of groups with a checkpoint: those among ``tasks`` stay one group, so that it continues from there."""
    return make_packs(sweep_groups(tasks, grouping, cost, packing, startup_s, saved), packing, startup_s)


def sweep_groups(tasks: Sequence[Mapping[str, Any]], grouping: Grouping, cost: Cost, packing: JobPacking,
                 startup_s: float, saved: Sequence[Sequence[str]] = ()) -> list[Group]:
    """The lockstep groups of ``tasks`` (manifest rows): first the checkpointed groups ``saved`` whose tasks are all
    among them, then the others, none predicted to outlast the largest time class when it can be split (unless a
    site cap makes long groups chains of jobs)."""
    by_id = {task["task_id"]: task for task in tasks}
    kept = [list(ids) for ids in saved if all(task_id in by_id for task_id in ids)]
    taken = {task_id for ids in kept for task_id in ids}
    longest_s = math.inf if packing.max_time_minutes else \
        60 * max(packing.time_classes_minutes) / packing.time_safety - startup_s
    if longest_s <= 0:
        raise ConfigError(f"cost.startup_s={cost.startup_s} leaves no time for a job's groups in the largest of "
                          f"packing.time_classes_minutes={list(packing.time_classes_minutes)} with time_safety="
                          f"{packing.time_safety}: lower it or add a larger class")
    return ([planned_group([by_id[task_id] for task_id in ids], cost, grouping) for ids in kept]
            + planned_groups([task for task in tasks if task["task_id"] not in taken], grouping, cost, longest_s))
