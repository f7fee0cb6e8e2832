"""Shared fixtures: composed configs and a trajectory cache per test session, shared by its xdist workers.

Every test trains on one thread, as a job does (``threads: 1``): torch's default of one per core made a test
take 30x longer with another process on the second core. The variables reach the commands tests run too."""

import os
from collections import Counter
from typing import Any

for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_variable] = "1"

import pytest  # noqa: E402 (after the variables: numpy reads them when it loads)
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402
from xdist.scheduler import LoadScopeScheduling  # noqa: E402

from nsl_hpc.config import compose_config  # noqa: E402
from nsl_hpc.core.cache import ArrayCache  # noqa: E402
from tests import clusters  # noqa: E402
from tests.sweeps import SHARED_CACHE  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory, worker_id) -> str:
    """The session's trajectory cache, one for all its xdist workers (in the session's temp dir, above each
    worker's): each trajectory is simulated once a run, not once per worker (the cache's writes are atomic and
    concurrent writers agree: test_datasets)."""
    root = tmp_path_factory.getbasetemp() if worker_id == "master" else tmp_path_factory.getbasetemp().parent
    path = root / "trajectory-cache"
    path.mkdir(exist_ok=True)
    return str(path)


@pytest.fixture(scope="session", autouse=True)
def shared_trajectories(cache_dir) -> None:
    """The launches of tests/sweeps.py's ``nsl`` simulate into ``cache_dir`` too."""
    os.environ[SHARED_CACHE] = cache_dir


@pytest.fixture(scope="session")
def cache(cache_dir) -> ArrayCache:
    return ArrayCache(cache_dir)


@pytest.fixture
def compose(cache_dir, tmp_path):
    """compose(*overrides) -> the task config with cache and out_dir inside this test's temp dirs."""

    def make(*overrides: str) -> DictConfig:
        return compose_config([f"cache_dir={cache_dir}", f"out_dir={tmp_path / 'out'}", *overrides])

    return make


def pytest_configure(config: pytest.Config) -> None:
    """Whether the second cluster answers, decided once, before the xdist workers start (they inherit it)."""
    if not hasattr(config, "workerinput") and clusters.SECOND not in os.environ and clusters.second_answers():
        os.environ[clusters.SECOND] = clusters.SECOND_CONF


class FileOrCluster(LoadScopeScheduling):
    """pytest-xdist's scheduling for ``make test`` (``-n 4``): the tests of one file run on one worker, in order,
    sharing their module fixtures, and the SLURM tests (tests/cluster/) of one cluster one after another on one
    worker: they share the cluster's queue and CPUs, and some restart it or change its limits. With the second
    cluster up, its files (``clusters.ON_SECOND``) run on another worker, beside the first's; a file of
    ``clusters.OWN_CLUSTER`` on a third. (xdist's loadgroup would do this with marks, but does not group anything under
    pytest 9.)"""

    def _split_scope(self, nodeid: str) -> str:
        path = nodeid.split("::", 1)[0]
        if not nodeid.startswith("tests/cluster/") or path in clusters.OWN_CLUSTER:
            return path
        return "cluster 2" if clusters.SECOND in os.environ and path in clusters.ON_SECOND else "cluster 1"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The SLURM tests first, then the files by their number of end-to-end and slow tests (most first), then the
    rest, each file's tests in their order: the workers take files in this order, so the longest start first and
    none is left to run alone at the end."""
    heavy = Counter(item.path for item in items if item.get_closest_marker("e2e") or item.get_closest_marker("slow"))
    items.sort(key=lambda item: (0, 0) if "cluster" in item.path.parts else (1, -heavy[item.path]))


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> FileOrCluster:
    config.option.loadscopereorder = False  # keep the order above, not xdist's default of the most tests first
    return FileOrCluster(config, log)


BUSY: Counter[str] = Counter()  # seconds of setup, call and teardown per xdist worker (the controller sees them all)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    gateway = getattr(getattr(report, "node", None), "gateway", None)  # a worker's report, on the controller
    BUSY[gateway.id if gateway else "main"] += report.duration


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """Each worker's busy time: the longest sets the run's wall time (make test: keep them even)."""
    if BUSY and "main" not in BUSY:  # under xdist
        terminalreporter.write_line("busy per worker: " + ", ".join(f"{worker} {seconds:.0f} s"
                                                                     for worker, seconds in sorted(BUSY.items())))
