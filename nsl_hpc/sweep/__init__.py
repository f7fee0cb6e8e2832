"""Turning a grid into tasks and running them: what a sweep directory holds, and how its jobs are planned,
submitted, run and accounted for.

    grid         sweep.grid -> tasks; the manifest table (coordinates and drawn sizes)
    manifest     the sweep directory's files: manifest.parquet, configs/, launch.yaml, run.yaml
    directory    one command per sweep at a time (the lock), control-file permissions, portable paths
    prepare      validate a launch, write the sweep's files, find the tasks still to run
    task         one task: validate, train, write its row
    rows         one Parquet row per task, written atomically; its state (done, corrupt, missing)
    failures     failure records and task logs
    plan         predicted times, lockstep groups, packs, time classes
    launchers    the launcher settings (local, debug, slurm), one dataclass each
    executors    run packs: SLURM job arrays or local processes
    job          what one job runs: its pack's lockstep groups, each watched
    slurm        the one seam to SLURM's commands
    submissions  what was submitted: one record per job array
    task_states  where every task stands (done, running, pending, failed, frozen, timeout, missing, corrupt)
"""
