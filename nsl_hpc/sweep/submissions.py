"""What was submitted to SLURM for a sweep: one record per job array,
``<sweep_dir>/submissions/<array id>.json`` with its time limit, submission time, element ids and the
task ids each element runs. ``status``, ``resubmit`` and ``clean`` read them."""

import json
import time
from collections.abc import Container, Mapping, Sequence
from pathlib import Path
from typing import Any

from nsl_hpc.core.atomic import write_text
from nsl_hpc.core.errors import damaged_file
from nsl_hpc.sweep import layout


def record_submission(sweep_dir: Path, array_id: str, time_limit_min: int, element_ids: Sequence[str],
                      elements: Sequence[Sequence[str]], seconds: Sequence[Sequence[float]], cluster: str = "") -> None:
    """Record an array whose element ``element_ids[i]`` runs the tasks ``elements[i]``, predicted to take
    ``seconds[i][j]`` for task j (its share of its lockstep group's prediction and of the job's start), submitted
    to the cluster named ``cluster`` (its ClusterName)."""
    record = {"array_id": array_id, "time_limit_min": time_limit_min, "submitted": time.time(),
              "element_ids": list(element_ids), "elements": [list(task_ids) for task_ids in elements],
              "task_seconds": [list(shares) for shares in seconds], "cluster": cluster}
    write_text(json.dumps(record), layout.submission_path(sweep_dir, array_id))


def read_submissions(sweep_dir: Path) -> list[dict[str, Any]]:
    """Every array submitted for the sweep, oldest first."""
    records = []
    for path in (Path(sweep_dir) / layout.SUBMISSIONS).glob("*.json"):
        try:
            record = json.loads(path.read_text())
            records.append((record["submitted"], record))
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise damaged_file(path, error) from None
    return [record for _, record in sorted(records, key=lambda pair: pair[0])]


def submitted_clusters(records: Sequence[Mapping[str, Any]]) -> set[str]:
    """The clusters ``records`` (read_submissions's) were submitted to (those recorded before the cluster was
    name none)."""
    return {record["cluster"] for record in records if record.get("cluster")}


def predicted_shares(records: Sequence[Mapping[str, Any]], wanted: Container[str] | None = None
                     ) -> dict[str, float]:
    """Each submitted task's predicted seconds as recorded when it was submitted last (``records``:
    read_submissions's; those that predate the predictions give none); ``wanted``: only those tasks'."""
    shares: dict[str, float] = {}
    for record in records:
        for task_ids, seconds in zip(record["elements"], record.get("task_seconds") or [None] * len(record["elements"]),
                                     strict=True):
            for index, task_id in enumerate(task_ids):
                if wanted is not None and task_id not in wanted:
                    continue
                if seconds is None:
                    shares.pop(task_id, None)
                else:
                    shares[task_id] = seconds[index]
    return shares
