"""Training sets from fractional trajectory counts, the shared test set, and the concurrent cache."""

import dataclasses
import multiprocessing

import numpy as np
import pytest

from nsl_hpc.config import system as system_groups
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.studies.input_state.data import (
    build_test_set,
    build_training_set,
    load_trajectory,
    split_trajectory_count,
    training_points,
)
from tests.helpers import system_settings


@pytest.mark.parametrize(("n_traj", "whole", "partial", "points"), [
    (0.1, 0, 100, 100),
    (0.2567, 0, 256, 256),
    (1.0, 1, 0, 1000),
    (2.5, 2, 500, 2500),
    (51.2, 51, 200, 51200),
    (3.9999, 3, 999, 3999),
])
def test_fractional_trajectory_counts(n_traj, whole, partial, points):
    assert split_trajectory_count(n_traj, 1000) == (whole, partial)
    assert training_points(n_traj, 1000) == points


def test_training_set_is_a_prefix_of_the_seed_pool(cache):
    cfg = system_settings("spring")
    small = build_training_set(cfg, seed=1, n_traj=1.25, cache=cache)
    large = build_training_set(cfg, seed=1, n_traj=2.0, cache=cache)
    other_seed = build_training_set(cfg, seed=2, n_traj=1.25, cache=cache)
    assert len(small) == 1250 and len(large) == 2000
    np.testing.assert_array_equal(small.x, large.x[:1250])
    np.testing.assert_array_equal(small.dx, large.dx[:1250])
    assert not np.allclose(small.x, other_seed.x)


def test_test_set_is_fixed_and_sized_by_config(cache, tmp_path):
    cfg = system_settings("ball")
    first = build_test_set(cfg, cache)
    again = build_test_set(cfg, ArrayCache(tmp_path / "fresh"))  # recomputed from scratch
    assert len(first) == cfg.test_set.trajectories * 1000  # 10 s at 0.01 s
    np.testing.assert_array_equal(first.x, again.x)
    train = build_training_set(cfg, seed=cfg.test_set.seed, n_traj=1.0, cache=cache)
    assert not np.allclose(train.x, first.x[:1000])  # test and train pools never coincide


def test_the_test_set_length_is_a_setting(cache):
    cfg = system_settings("ball")
    short, long = (build_test_set(dataclasses.replace(cfg, test_set=system_groups.TestSet(2, seconds, seed=5)), cache)
                   for seconds in (10.0, 100.0))
    assert (len(short), len(long)) == (2 * 1000, 2 * 10_000)
    assert np.all(np.isfinite(long.dx)) and not np.allclose(long.x[:1000], short.x[:1000])  # a test set of its own


def test_cache_hit_returns_stored_arrays_without_recomputing(tmp_path):
    cache = ArrayCache(tmp_path)
    calls = []

    def create():
        calls.append(1)
        return {"a": np.arange(3.0)}

    first = cache.get_or_create({"k": 1}, create)
    second = cache.get_or_create({"k": 1}, create)
    assert len(calls) == 1
    np.testing.assert_array_equal(first["a"], second["a"])


def test_corrupt_cache_entry_is_recomputed(tmp_path):
    cache = ArrayCache(tmp_path)
    path = cache.path_for({"k": 2})
    path.parent.mkdir(parents=True)
    path.write_bytes(b"half a file")
    arrays = cache.get_or_create({"k": 2}, lambda: {"a": np.ones(2)})
    np.testing.assert_array_equal(arrays["a"], np.ones(2))
    np.testing.assert_array_equal(np.load(path)["a"], np.ones(2))


def load_in_subprocess(root: str) -> bytes:
    cfg = system_settings("motor")
    return load_trajectory(cfg, "train", 5, 0, ArrayCache(root)).x.tobytes()


@pytest.mark.slow
def test_concurrent_writers_of_one_trajectory_agree(tmp_path):
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        results = pool.map(load_in_subprocess, [str(tmp_path)] * 8)
    assert len(set(results)) == 1
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(files) == 1 and files[0].suffix == ".npz"  # no temporary file left behind
