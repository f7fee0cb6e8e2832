"""The shared base every other part of the package stands on, importing nothing of the package but itself.

    errors       the errors a command turns into one line on stderr, and the checks of single values
    atomic       atomic writes (a temporary file renamed into place)
    seeding      stable hashes and the seeds drawn from them
    cache        the simulated-data cache (one .npz file per key)
    checkpoint   a training loop's state on disk
    diagnostics  where the package's log records go
    progress     a bar, or counted lines, for a long phase
    law          the broken power law as a value (numpy alone)
"""
