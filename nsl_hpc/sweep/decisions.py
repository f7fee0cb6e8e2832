"""A budgeted sweep's decisions on disk (``budget/round-<r>.parquet``: which tasks of each round run, and why the
others do not) and the job that launches its next round on SLURM; what merge, status and the task states read
of a budget. The rule that makes the decisions is nsl_hpc/sweep/budget.py."""

import json
from collections import defaultdict
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from nsl_hpc.core.atomic import write_parquet, write_text
from nsl_hpc.core.errors import ConfigError, damaged_file
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.formats import upgrade_decisions
from nsl_hpc.sweep.slurm import ACTIVE_JOB_STATES, job_states, slurm_command

# one row per task of a decided round; cost_s: the predicted core-seconds it is charged (0 when skipped); resource:
# the result column whose envelope made it promising (null in round 1; rounds decided before it was recorded)
DECISION_SCHEMA = pa.schema([("task_id", pa.string()), ("round", pa.int64()), ("run", pa.bool_()),
                             ("reason", pa.string()), ("promise", pa.float64()), ("cost_s", pa.float64()),
                             ("resource", pa.string())])


def skip_reasons(decisions: Sequence[Mapping[str, Any]], ran: Collection[str] = ()) -> dict[str, int]:
    """Why the skipped tasks of ``decisions`` (but those in ``ran``: run since, by hand) were: reason -> tasks."""
    reasons: dict[str, int] = defaultdict(int)
    for d in decisions:
        if not d["run"] and d["task_id"] not in ran:
            reasons[d["reason"]] += 1
    return dict(reasons)


def describe_rounds(decisions: Sequence[Mapping[str, Any]]) -> str:
    """Rounds decided, predicted core-hours committed, tasks skipped and why (launch and status print it)."""
    decided = max((d["round"] for d in decisions), default=0)
    committed = sum(d["cost_s"] for d in decisions if d["run"]) / 3600
    reasons = skip_reasons(decisions)
    skipped = sum(reasons.values())
    return (f"{decided} round{'s' * (decided != 1)} decided, {committed:,.3g} predicted core-hours committed, "
            f"{skipped:,} tasks skipped" + (f" ({', '.join(f'{n:,} {why}' for why, n in sorted(reasons.items()))})"
                                            if skipped else ""))


def decision_files(sweep_dir: Path) -> list[Path]:
    """The decided rounds' files, in round order."""
    return sorted((Path(sweep_dir) / layout.BUDGET).glob("round-*.parquet"))


def read_decisions(sweep_dir: Path) -> list[dict[str, Any]]:
    """Every round's decisions written so far (a damaged file is refused in one line)."""
    decisions = []
    for path in decision_files(sweep_dir):
        try:
            table = upgrade_decisions(pq.read_table(path))
            decisions += table.select(DECISION_SCHEMA.names).cast(DECISION_SCHEMA).to_pylist()
        except (OSError, pa.ArrowException, KeyError) as error:
            raise damaged_file(path, error) from None
    return decisions


def budget_states(sweep_dir: Path) -> dict[str, str]:
    """Task id -> "skipped" for the tasks a budgeted sweep's rounds decided not to run, "to run" for the others
    decided; empty for a sweep without a budget."""
    return {d["task_id"]: "to run" if d["run"] else "skipped" for d in read_decisions(sweep_dir)}


def without_row_state(budgeted: Mapping[str, str], task_id: str, launching: bool) -> str:
    """The state of a task without a row, failure or job (``budgeted``: ``budget_states``): missing; in a budgeted
    sweep skipped where its round decided not to run it, waiting while its round is not decided; pending instead
    of missing or waiting while a launch or resubmit holds the sweep (it runs them, or decides their round)."""
    decision = budgeted.get(task_id, "waiting") if budgeted else "to run"
    state = "missing" if decision == "to run" else decision
    return "pending" if launching and state != "skipped" else state


def record_round_job(sweep_dir: Path, job_id: str) -> None:
    """Remember the SLURM job that launches the next round (``round_job_queued`` asks about it)."""
    write_text(json.dumps({"job_id": job_id}), layout.round_job_path(sweep_dir))


def queued_round_job(sweep_dir: Path) -> str | None:
    """The id of the job that launches a budgeted sweep's next round while it is pending or running in SLURM."""
    path = layout.round_job_path(sweep_dir)
    if not path.exists():
        return None
    try:
        job_id = str(json.loads(path.read_text())["job_id"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise damaged_file(path, error) from None
    return job_id if job_states([job_id]).states.get(job_id) in ACTIVE_JOB_STATES else None


def round_job_queued(sweep_dir: Path) -> bool:
    return queued_round_job(sweep_dir) is not None


def cancel_round_job(sweep_dir: Path) -> None:
    """Cancel the queued job of an earlier launch that would launch the next round (a later launch's replaces it)."""
    if (job_id := queued_round_job(sweep_dir)) is not None:
        slurm_command("scancel", job_id)


def write_decisions(sweep_dir: Path, number: int, decisions: Sequence[Mapping[str, Any]],
                    structure: tuple[int, int]) -> None:
    """Write round ``number``'s decisions (atomically) with the round structure they assume: (levels of round 1,
    levels per later round)."""
    table = pa.Table.from_pylist([dict(d) for d in decisions], schema=DECISION_SCHEMA)
    table = table.replace_schema_metadata({"first_levels": str(structure[0]), "levels_per_round": str(structure[1])})
    write_parquet(table, layout.round_decisions_path(sweep_dir, number))


def decided_structure(sweep_dir: Path) -> tuple[int, int] | None:
    """(levels of round 1, levels per later round) of the rounds already decided (None before round 1); rounds
    decided with different structures are refused."""
    structures = set()
    for path in decision_files(sweep_dir):
        try:
            stored = pq.read_schema(path).metadata or {}
        except (OSError, pa.ArrowException) as error:
            raise damaged_file(path, error) from None
        structures.add((int(stored.get(b"first_levels", 0)), int(stored.get(b"levels_per_round", 0))))
    if len(structures) > 1:
        raise ConfigError(f"{layout.BUDGET} of sweep_dir={str(sweep_dir)!r} holds rounds of different structures "
                          f"({sorted(structures)}): its decisions were edited by hand")
    return structures.pop() if structures else None
