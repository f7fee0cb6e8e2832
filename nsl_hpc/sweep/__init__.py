"""Turning a grid into tasks and running them: what a sweep directory holds, and how its jobs are planned,
submitted, run and accounted for.

    grid         sweep.grid -> tasks; the manifest table (coordinates and drawn sizes)
    layout       the sweep directory's file and folder names, in one place
    manifest     the sweep directory's files: manifest.parquet, configs/, launch.yaml, run.yaml
    directory    one command per sweep at a time (the lock), control-file permissions, portable paths
    storage      whether the file system holds the sweep: free space, inodes, flock
    limits       the cluster's own limits (MaxArraySize, partition MaxTime, association and QOS), read first
    prepare      validate a launch, write the sweep's files, find the tasks still to run
    task         one task: validate, train, write its row
    rows         one Parquet row per task, written atomically; its state (done, corrupt, missing)
    failures     failure records and task logs
    groups       where lockstep groups keep their training checkpoints, and the lock of a group
    plan         predicted times, lockstep groups, packs, time classes
    executors    run packs: SLURM job arrays or local processes
    job          what one job runs: its pack's lockstep groups, each watched
    slurm        the one seam to SLURM's commands
    submissions  what was submitted: one record per job array
    task_states  where every task stands (done, running, pending, failed, frozen, timeout, missing, corrupt)
    merge        the rows into results.parquet (compacted as it goes), and what was dropped and why
    budget       budgeted sweeps: the budget, and the rule that decides which of a round's tasks run
    rounds       a budgeted sweep's rounds along the length axis, deciding the next one, and the loop that runs them
    decisions    a budgeted sweep's decisions on disk, and the job that launches its next round
    rehearsal    the whole sweep through the real path with outcomes drawn from planted laws

The launcher settings' schema is nsl_hpc/config/launchers.py.
"""
