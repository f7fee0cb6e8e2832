"""A rehearsal (``launch ... rehearsal=true``): the whole sweep through the real path (plan, packing, arrays,
jobs, group locks, rows, watchdog, status, resubmit, merge, fit) for minutes of core time. No task trains: its
outcome is drawn from the planted compute laws of ``rehearse.laws`` (one per metric, every (system, arch) the
same), and faults strike at the study's rates, decided by hashes of task ids (a task's outcome and faults depend
only on its config):

- an outcome: L(c) exp(s) at the task's compute c (flops), s = |N(0, near_sd)| for a ``near_share`` of the tasks
  (trained well: the envelope converges to the law from above) and that plus Exp(far_mean) for the rest; nMSE
  has its own law and 2 s;
- a lockstep group freezes (no heartbeat: the watchdog stops it after ``rehearse.heartbeat_timeout_s``) or fails
  (raises) at every attempt, ``frozen_share`` and ``failed_share`` of the groups;
- ``killed_jobs`` jobs of a launch are killed (SIGKILL, as by a lost node or the OOM killer) after their first
  group, once: resubmit runs what they left.

Every row says ``rehearsal: true``; fit and report set the planted law beside the fitted one and say so on
every figure. The law is the fits' (``nsl_hpc.core.law``): the rehearsal plants what they fit.
"""

import math
import os
import signal
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nsl_hpc.config.schema import setting
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.core.law import NSLFit
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.plan import Pack
from nsl_hpc.sweep.run_settings import DAY_S

METRICS = ("nmae", "nmse")


@dataclass(frozen=True)
class PlantedLaw:
    """L(c) = alpha + beta c^delta0 prod_i [1 + (c / sigma_i)^(1 / phi_i)]^(delta_i phi_i), as
    conf/published_laws.yaml writes laws."""

    alpha: float = setting("the floor", 0)
    beta: float = setting("the scale", 0, low_open=True)
    delta0: float = setting("the first slope")
    breaks: list[list[float]] = setting("[sigma, phi, delta] per break")

    def check(self) -> None:
        if any(len(brk) != 3 or brk[0] <= 0 or brk[1] <= 0 for brk in self.breaks):
            raise ConfigError(f"rehearse.laws: breaks={self.breaks} must be [sigma, phi, delta] triples with sigma "
                              "and phi above 0")


@dataclass(frozen=True)
class Rehearse:
    """A rehearsal's planted laws and faults (conf/config.yaml)."""

    laws: dict[str, PlantedLaw] = setting("the planted compute law of each metric (nmae, nmse)")
    near_share: float = setting("share of the tasks trained as well as the law allows", 0, 1)
    near_sd: float = setting("their log(e / L) = |N(0, near_sd)|", 0)
    far_mean: float = setting("the others add Exp(far_mean) to that", 0)
    frozen_share: float = setting("share of lockstep groups that freeze at every attempt", 0, 1)
    failed_share: float = setting("share of lockstep groups that fail at every attempt", 0, 1)
    killed_jobs: int = setting("jobs of a launch killed after their first group, once", 0)
    heartbeat_timeout_s: float = setting("the watchdog's patience in a rehearsal's jobs (s)", 0, DAY_S,
                                         low_open=True)

    def check(self) -> None:
        if sorted(self.laws) != sorted(METRICS):
            raise ConfigError(f"rehearse.laws has {', '.join(sorted(self.laws))}: it needs a law for each of "
                              f"{', '.join(METRICS)}")
        if self.frozen_share + self.failed_share > 1:
            raise ConfigError(f"rehearse.frozen_share + rehearse.failed_share = "
                              f"{self.frozen_share + self.failed_share:g}: at most 1 (a share of the groups)")


def planted_law(rehearse: Rehearse, metric: str) -> NSLFit:
    """The planted compute law of ``metric`` (``rehearse.laws``)."""
    law = rehearse.laws[metric]
    breaks = [(float(sigma), float(phi), float(delta)) for sigma, phi, delta in law.breaks]
    return NSLFit(float(law.alpha), float(law.beta), float(law.delta0), breaks, 0.0, np.empty(0), np.empty(0))


def share_drawn(purpose: str, key: str) -> float:
    """A number in [0, 1) fixed by ``purpose`` and ``key`` (a task or group id)."""
    return stable_seed("rehearsal", purpose, key) / 2**63


def drawn_scores(rehearse: Rehearse, flops: float, rng: np.random.Generator) -> dict[str, float]:
    """Each metric's score of a task of ``flops`` compute: its planted law there times exp(s) (nMSE: exp(2 s)),
    s = |N(0, near_sd)|, plus Exp(far_mean) for a task outside the ``near_share``."""
    spread = abs(rng.normal(0.0, rehearse.near_sd))
    if rng.random() >= rehearse.near_share:
        spread += rng.exponential(rehearse.far_mean)
    return {metric: float(planted_law(rehearse, metric).predict(flops)) * math.exp(spread * (1 + (metric == "nmse")))
            for metric in METRICS}


def rehearsed_outcome(rehearse: Rehearse, task_id: str, sizes: Mapping[str, Any]) -> dict[str, Any]:
    """The outcome of one task of a rehearsal: its scores drawn at its compute (``sizes['flops']``), the study's
    training length (``sizes['steps']``), nothing trained."""
    rng = np.random.default_rng(stable_seed("rehearsal", "outcome", task_id))
    scores = drawn_scores(rehearse, float(sizes["flops"]), rng)
    return {**scores, "steps": int(sizes["steps"]), "final_loss": scores["nmse"], "train_seconds": 0.0,
            "finite": True, "compiled": False, "rehearsal": True}


def strike_group(rehearse: Rehearse, task_ids: Sequence[str], on_progress: Any) -> None:
    """The fault a rehearsal's lockstep group meets at every attempt: none, or it freezes (one heartbeat, then
    none) or fails (raises)."""
    drawn = share_drawn("group", task_ids[0])
    if drawn < rehearse.frozen_share:
        on_progress()
        while True:
            time.sleep(3600)
    if drawn < rehearse.frozen_share + rehearse.failed_share:
        raise RuntimeError(f"rehearsal: a failure planted in the group of {len(task_ids)} tasks of {task_ids[0]}")


def rehearsed_group(rehearse: Rehearse, items: Sequence[tuple[str, Mapping[str, Any]]], on_progress: Any
                    ) -> list[dict[str, Any]]:
    """The outcomes of a rehearsal's lockstep group of (task id, sizes) ``items``, or its planted fault."""
    strike_group(rehearse, [task_id for task_id, _ in items], on_progress)
    on_progress()
    return [rehearsed_outcome(rehearse, task_id, sizes) for task_id, sizes in items]


def plant_job_deaths(sweep_dir: Path, rehearse: Rehearse, packs: Sequence[Pack]) -> None:
    """Choose the ``rehearse.killed_jobs`` jobs of a launch that will be killed after their first group (of those
    with more groups, if any: their others are left unrun; in the order of a hash of their first task id): a file
    ``<sweep_dir>/rehearsal/kill-<first task id>`` each (a local worker dies after that group)."""
    candidates = [pack for pack in packs if len(pack.groups) > 1] or list(packs)
    chosen = sorted((pack.task_ids[0] for pack in candidates),
                    key=lambda task_id: share_drawn("job", task_id))[:rehearse.killed_jobs]
    for task_id in chosen:
        marker = Path(sweep_dir) / layout.REHEARSAL / f"kill-{task_id}"
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()


def die_if_planted(sweep_dir: Path, first_task_id: str) -> None:
    """Kill this job (SIGKILL: what a lost node or the OOM killer does) if its death was planted behind the group
    of ``first_task_id`` (``plant_job_deaths``), once: the file that planted it is renamed ``killed-<task id>``
    first."""
    marker = Path(sweep_dir) / layout.REHEARSAL / f"kill-{first_task_id}"
    try:
        marker.rename(marker.with_name(f"killed-{first_task_id}"))
    except FileNotFoundError:
        return
    os.kill(os.getpid(), signal.SIGKILL)
