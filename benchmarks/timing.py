"""Wall-clock timing for the benchmark scripts."""

import time


def timed(function, *args):
    """(function(*args), seconds it took)."""
    started = time.perf_counter()
    result = function(*args)
    return result, time.perf_counter() - started
