"""Where a sweep stands: done / running / pending / failed / frozen / timeout / missing tasks, a progress
bar with an ETA, and the failed tasks with the last lines of their logs.

    python -m nsl_hpc.status sweep_dir=runs/demo
    python -m nsl_hpc.status sweep_dir=runs/input_state wait=true     # until nothing runs or waits

`missing` tasks have no row, no failure record and no active job (cancelled, lost, never submitted);
`corrupt` ones a file where their row belongs that is no valid row (truncated, overwritten; each row file is
read once while it is the same file, so one damaged in place is seen by merge, which reads every row):
`python -m nsl_hpc.resubmit sweep_dir=<dir>` runs them again, with the failed ones. In a budgeted sweep,
`skipped` tasks were decided not to run and `waiting` ones wait for their round (launch decides it); with
`budget.track_laws`, how wide the laws' 90% intervals were on the rows of the rounds so far, and which resource
narrowed most per core-hour in the latest round. Groups
with a training checkpoint are listed with their progress and how often they were resumed (a time cap's chain,
a preemption, a requeue, a resubmit after a crash): `running (resumed 2 times)`.
"""

import time
from collections import Counter
from dataclasses import dataclass

import pyarrow as pa
import pyarrow.compute as pc
from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.sweep.decisions import describe_rounds, read_decisions, round_job_queued
from nsl_hpc.sweep.groups import held_locks, saved_groups
from nsl_hpc.sweep.launch_settings import LaunchSettings, launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, read_manifest, require_sweep
from nsl_hpc.sweep.rows import refuse_pandas
from nsl_hpc.sweep.task_states import STATES, SweepState, read_sweep_state

LOG_LINES = 5  # log lines shown per failed task


@dataclass(frozen=True)
class StatusSettings:
    """status's own keys (conf/status.yaml)."""

    sweep_dir: str = setting("the sweep directory (holds manifest.parquet)")
    wait: bool = setting("keep watching until no task is running or pending")
    interval_s: float = setting("first interval between looks when waiting (then x1.5, up to max_interval_s)", 0,
                                86400, low_open=True)
    max_interval_s: float = setting("the longest interval between looks", 0, 86400, low_open=True)
    settle_s: float = setting("when waiting ends with tasks missing or waiting, look once more after this", 0, 86400)
    show_failures: int = setting("failed / frozen / timeout tasks listed with the end of their logs", 0)


def remaining_seconds(sweep_dir, state: SweepState, launch: LaunchSettings) -> float:
    """Predicted core-seconds of the tasks without a row: a submitted task's share of what its array element was
    predicted to take, the others in the lockstep groups the planner makes of them; a group with a checkpoint:
    the share of its steps still to train."""
    todo = {task_id for task_id in state.not_done if state.states[task_id] not in ("skipped", "waiting")}
    shares = state.predicted_s
    saved = {group.task_ids: group for group in saved_groups(sweep_dir)}
    left = {task_id: 1 - group.step / max(group.total_steps, 1)
            for group in saved.values() for task_id in group.task_ids}
    never_submitted = todo - shares.keys()
    unplanned = []
    if never_submitted:
        manifest = read_manifest(sweep_dir)
        unplanned = manifest.filter(pc.is_in(manifest["task_id"], value_set=pa.array(sorted(never_submitted)))
                                    ).to_pylist()
    groups = launch.groups(unplanned, list(saved)) if unplanned else []
    return (sum(shares[task_id] * left.get(task_id, 1.0) for task_id in todo if task_id in shares)
            + sum(group.seconds * left.get(group.task_ids[0], 1.0) for group in groups))


def running_cores(sweep_dir, state: SweepState) -> int:
    """Cores training the sweep now: its running SLURM array elements, or the local workers holding a group."""
    elements = sum(element_state == "RUNNING" for element_state in state.element_states.values())
    return max(elements, len({(lock.host, lock.pid) for lock in held_locks(sweep_dir) if lock.live}))


def summary(state: SweepState, seconds: float, cores: int) -> str:
    """The counts by state, a progress bar and the time left: ``seconds`` of predicted work on ``cores``."""
    counts = state.counts
    total = len(state.states)
    bar_width = 40
    filled = round(bar_width * counts["done"] / total)
    hours = seconds / 3600
    eta = (f"ETA {hours / cores:.1f} h on {cores} core{'s' * (cores != 1)} running" if cores
           else f"{hours:.1f} core-hours left")
    line = " | ".join(f"{name} {counts[name]:,}" for name in STATES)
    return (f"{total:,} tasks: {line}\n[{'#' * filled}{'.' * (bar_width - filled)}] "
            f"{100 * counts['done'] / total:.1f}% done, {eta}")


def checkpoint_report(sweep_dir, state: SweepState, limit: int) -> str:
    """A line per group with a checkpoint and tasks without a row: their state, resumes and progress."""
    lines, now = [], time.time()
    groups = [saved for saved in saved_groups(sweep_dir)
              if any(state.states.get(task_id) not in (None, "done") for task_id in saved.task_ids)]
    for saved in groups[:limit]:
        states = Counter(state.states.get(task_id) for task_id in saved.task_ids)
        label = "running" if states["running"] else states.most_common(1)[0][0]
        lines.append(f"{label} (resumed {saved.resumes} time{'' if saved.resumes == 1 else 's'}): "
                     f"{len(saved.task_ids)} task{'' if len(saved.task_ids) == 1 else 's'} in a group at step "
                     f"{saved.step:,} of {saved.total_steps:,}, checkpoint written {now - saved.saved:.0f} s ago")
    if len(groups) > limit:
        lines.append(f"... and {len(groups) - limit:,} more groups with a checkpoint")
    return "\n".join(lines)


def failure_report(state: SweepState, limit: int) -> str:
    failed = state.tasks_in(("failed", "frozen", "timeout"))
    lines = []
    for task in failed[:limit]:
        record = state.failures[task["task_id"]]
        lines.append(f"{record['status']} {task['task_id']} ({task['system']}/{task['arch']} seed={task['seed']} "
                     f"steps={task['steps']:,}): {record['reason']}")
        lines += [f"    | {line}" for line in record["log_tail"].splitlines()[-LOG_LINES:]]
    if len(failed) > limit:
        lines.append(f"... and {len(failed) - limit:,} more (show_failures=N lists more)")
    return "\n".join(lines)


def main(config: DictConfig) -> int:
    refuse_pandas()  # pyarrow would import it to convert the sweep's tables: 0.35 s of every look
    cfg = typed(StatusSettings, config, "")
    sweep_dir = require_sweep(cfg.sweep_dir)
    launch = launch_settings(read_launch_config(sweep_dir))
    interval, confirming = cfg.interval_s, False
    while True:
        state = read_sweep_state(sweep_dir)
        print(summary(state, remaining_seconds(sweep_dir, state, launch), running_cores(sweep_dir, state)),
              flush=True)
        if note := state.accounting_note():
            print(note, flush=True)
        if decisions := read_decisions(sweep_dir):
            from nsl_hpc.analysis.widths import describe_law_records, law_records  # scipy: a budget's only

            print(f"budget: {describe_rounds(decisions)}", flush=True)
            stop_when = launch.budget.stop_when if launch.budget is not None else None
            for line in describe_law_records(law_records(sweep_dir), stop_when):
                print(line, flush=True)
        counts = state.counts
        active = counts["running"] + counts["pending"] + (
            counts["waiting"] if round_job_queued(sweep_dir) else 0)  # the next round comes
        unsettled = counts["missing"] + counts["waiting"]
        if not cfg.wait or (not active and (confirming or not unsettled)):
            break
        if not active:  # a job being requeued, or a round job sacct does not list yet, can look ended for a
            # moment: look again before calling its tasks missing or left waiting
            confirming = True
            time.sleep(cfg.settle_s)
            continue
        confirming = False
        time.sleep(interval)
        interval = min(interval * 1.5, cfg.max_interval_s)  # back off: sites rate-limit sacct
    for report in (checkpoint_report(sweep_dir, state, cfg.show_failures),
                   failure_report(state, cfg.show_failures)):
        if report:
            print(report)
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="status")
