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
- a job is killed (SIGKILL, as by a lost node or the OOM killer) after its first group, ``killed_job_share`` of
  the jobs, at its first attempt only: resubmit runs what it left.

Every row says ``rehearsal: true``; fit and report set the planted law beside the fitted one and say so on
every figure. The law is the fits' (``analysis.law``): the rehearsal plants what they fit.
"""

import math
import os
import signal
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nsl_hpc.analysis.law import NSLFit
from nsl_hpc.seeding import stable_seed
from nsl_hpc.sweep import layout

METRICS = ("nmae", "nmse")


def planted_law(rehearse: Mapping[str, Any], metric: str) -> NSLFit:
    """The planted compute law of ``metric`` (``rehearse.laws``)."""
    law = rehearse["laws"][metric]
    breaks = [(float(sigma), float(phi), float(delta)) for sigma, phi, delta in law["breaks"]]
    return NSLFit(float(law["alpha"]), float(law["beta"]), float(law["delta0"]), breaks, 0.0, np.empty(0),
                  np.empty(0))


def share_drawn(purpose: str, key: str) -> float:
    """A number in [0, 1) fixed by ``purpose`` and ``key`` (a task or group id)."""
    return stable_seed("rehearsal", purpose, key) / 2**63


def rehearsed_outcome(rehearse: Mapping[str, Any], task_id: str, sizes: Mapping[str, Any]) -> dict[str, Any]:
    """The outcome of one task of a rehearsal: its scores drawn at its compute (``sizes['flops']``), the study's
    training length (``sizes['steps']``), nothing trained."""
    rng = np.random.default_rng(stable_seed("rehearsal", "outcome", task_id))
    spread = abs(rng.normal(0.0, rehearse["near_sd"]))
    if rng.random() >= rehearse["near_share"]:
        spread += rng.exponential(rehearse["far_mean"])
    flops = float(sizes["flops"])
    scores = {metric: float(planted_law(rehearse, metric).predict(flops)) * math.exp(spread * (1 + (metric == "nmse")))
              for metric in METRICS}
    return {**scores, "steps": int(sizes["steps"]), "final_loss": scores["nmse"], "train_seconds": 0.0,
            "finite": True, "compiled": False, "rehearsal": True}


def strike_group(rehearse: Mapping[str, Any], task_ids: Sequence[str], on_progress: Any) -> None:
    """The fault a rehearsal's lockstep group meets at every attempt: none, or it freezes (one heartbeat, then
    none) or fails (raises)."""
    drawn = share_drawn("group", task_ids[0])
    if drawn < rehearse["frozen_share"]:
        on_progress()
        while True:
            time.sleep(3600)
    if drawn < rehearse["frozen_share"] + rehearse["failed_share"]:
        raise RuntimeError(f"rehearsal: a failure planted in the group of {len(task_ids)} tasks of {task_ids[0]}")


def rehearsed_group(rehearse: Mapping[str, Any], items: Sequence[tuple[str, Mapping[str, Any]]], on_progress: Any
                    ) -> list[dict[str, Any]]:
    """The outcomes of a rehearsal's lockstep group of (task id, sizes) ``items``, or its planted fault."""
    strike_group(rehearse, [task_id for task_id, _ in items], on_progress)
    on_progress()
    return [rehearsed_outcome(rehearse, task_id, sizes) for task_id, sizes in items]


def kill_job_once(sweep_dir: Path, rehearse: Mapping[str, Any], first_task_id: str) -> None:
    """Kill this job (SIGKILL) if the rehearsal plants its death and it has not died yet (a marker file under
    ``<sweep_dir>/rehearsal/`` remembers it): what a lost node or the OOM killer does."""
    if share_drawn("job", first_task_id) >= rehearse["killed_job_share"]:
        return
    marker = Path(sweep_dir) / layout.REHEARSAL / f"killed-{first_task_id}"
    if marker.exists():
        return
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    os.kill(os.getpid(), signal.SIGKILL)
