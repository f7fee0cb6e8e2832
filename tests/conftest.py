"""Shared fixtures: composed configs and a private trajectory cache per test session."""

import pytest
from omegaconf import DictConfig

from nsl_hpc.cache import ArrayCache
from nsl_hpc.config import compose_config


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("trajectory-cache"))


@pytest.fixture(scope="session")
def cache(cache_dir) -> ArrayCache:
    return ArrayCache(cache_dir)


@pytest.fixture
def compose(cache_dir, tmp_path):
    """compose(*overrides) -> the task config with cache and out_dir inside this test's temp dirs."""

    def make(*overrides: str) -> DictConfig:
        return compose_config([f"cache_dir={cache_dir}", f"out_dir={tmp_path / 'out'}", *overrides])

    return make
