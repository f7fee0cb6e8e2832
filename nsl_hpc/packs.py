"""The job runner's old address. Jobs submitted by nsl_hpc 0.1 unpickle ``nsl_hpc.packs.PackRunner`` and pass it
a pack's task ids: this shim regroups them as 0.1 did and runs them with ``nsl_hpc.sweep.job.JobRunner``.
Remove it once no job submitted by 0.1 is queued or can be requeued (every sweep launched or resubmitted
with 0.1 has finished).
"""

from collections.abc import Sequence
from pathlib import Path

import submitit

from nsl_hpc.sweep.job import JobRunner, manifest_rows
from nsl_hpc.sweep.manifest import read_launch_config
from nsl_hpc.sweep.plan import Group, packing_for, sweep_groups


def legacy_groups(sweep_dir: str, task_ids: Sequence[str]) -> list[Group]:
    """The lockstep groups 0.1's runner formed from a pack's task ids (with the sweep's run settings)."""
    launch = read_launch_config(Path(sweep_dir))
    return sweep_groups(manifest_rows(Path(sweep_dir), task_ids), launch, packing_for(launch.packing, launch.launcher))


class PackRunner(JobRunner):
    """0.1's job runner: ``PackRunner(launcher_pid)(sweep_dir, task_ids)``."""

    def __call__(self, sweep_dir: str, task_ids: Sequence[str]) -> dict[str, int]:
        return super().__call__(sweep_dir, legacy_groups(sweep_dir, task_ids))

    def checkpoint(self, sweep_dir: str, task_ids: Sequence[str]) -> submitit.helpers.DelayedSubmission | None:
        return super().checkpoint(sweep_dir, legacy_groups(sweep_dir, task_ids))
