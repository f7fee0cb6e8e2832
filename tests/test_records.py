"""Input-output records: the stand-ins' shapes and determinism, the measured files through the real
nonlinear_benchmarks loader path (when ../shared/data holds them), and bad data files."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from nsl_hpc.config import compose_config
from nsl_hpc.config.system import InputOutputSystem
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.place_data import main as place_data
from nsl_hpc.studies.input_output.data import load_benchmark
from tests.helpers import system_settings

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MEASURED = pytest.mark.skipif(not (SHARED_DATA / "silverbox" / "SNLS80mV.mat").is_file(),
                              reason="no measured copies in ../shared/data")


def io_system(name: str, **source) -> InputOutputSystem:
    """The typed input-output system ``name``, its source's ``data_dir`` (...) replaced."""
    system = system_settings(name, "study=input_output")
    return dataclasses.replace(system, source=dataclasses.replace(system.source, **source))


@pytest.mark.parametrize(("name", "train", "validation", "test"), [
    ("silverbox_sim", 64_000, 1_062, 40_475), ("wiener_hammerstein_sim", 80_000, 20_000, 78_800)])
def test_stand_ins_have_the_benchmarks_shapes_and_are_reproducible(name, train, validation, test, cache, tmp_path):
    records = load_benchmark(io_system(name), cache)
    assert (len(records.train), len(records.validation), len(records.tests["test"])) == (train, validation, test)
    for record in (records.train, records.validation, records.tests["test"]):
        assert record.u.shape == record.y.shape and np.isfinite(record.y).all()
        assert 0.01 < record.y.std() < 1.0  # volts, like the measured records
    fresh = load_benchmark(io_system(name), ArrayCache(tmp_path))  # simulated again, not read from the cache
    assert np.array_equal(fresh.tests["test"].y, records.tests["test"].y)
    assert np.array_equal(fresh.train.u, records.train.u)
    assert not np.allclose(records.train.u[:1000], records.tests["test"].u[:1000])  # separate input realisations


@MEASURED
def test_measured_records_load_through_the_loader_with_the_official_split_sizes(tmp_path, cache):
    place_data(compose_config([f"source={SHARED_DATA}", f"data_dir={tmp_path}"], "place_data"))
    silverbox = load_benchmark(io_system("silverbox", data_dir=str(tmp_path)), cache)
    assert (len(silverbox.train), len(silverbox.validation)) == (64_000, 1_062)
    assert list(silverbox.tests) == ["multisine", "arrow_full", "arrow_no_extrapolation"]
    assert len(silverbox.tests["arrow_full"]) == 40_475
    assert silverbox.tests["arrow_full"].y.std() == pytest.approx(0.05345, abs=1e-4)  # arrow (full): 53.45 mV
    wh = load_benchmark(io_system("wiener_hammerstein", data_dir=str(tmp_path)), cache)
    assert (len(wh.train), len(wh.validation), len(wh.tests["test"])) == (80_000, 20_000, 78_800)
    assert wh.tests["test"].y.std() == pytest.approx(0.24386, abs=1e-4)


@MEASURED
def test_the_process_noise_benchmark_trains_on_its_realisations_in_turn_and_tests_on_both_records(tmp_path, cache):
    place_data(compose_config([f"source={SHARED_DATA}", f"data_dir={tmp_path}"], "place_data"))
    records = load_benchmark(io_system("wiener_hammerstein_process_noise", data_dir=str(tmp_path)), cache)
    assert (len(records.train), len(records.validation)) == (80_000, 1_920)  # 10 x 8,192 samples
    assert list(records.tests) == ["multisine", "swept_sine"]
    assert records.tests["multisine"].y.std() == pytest.approx(0.1283, abs=1e-4)  # the README's 128.3 mV
    assert records.tests["swept_sine"].y.std() == pytest.approx(0.0796, abs=1e-4)  # and 79.6 mV
    with np.load(SHARED_DATA / "wh_process_noise" / "WH_EstimationExample.npz") as estimation:
        assert np.array_equal(records.train.y[8192:16384], estimation["y"][:, 1])  # realisation 2 after 1
        assert np.array_equal(records.validation.u, estimation["u"][-1920:, 9])


@MEASURED
def test_placed_files_are_kept_and_a_benchmark_no_folder_holds_is_one_line_naming_its_page(tmp_path, capsys):
    """A second placing keeps what is there; a system whose files no source folder holds and that is not
    downloaded (download=false here; where the machine cannot reach the loader's server, the same line follows a
    failed download) says where its files are published, and what was placed before it stays."""
    place_data(compose_config([f"source={SHARED_DATA}", f"data_dir={tmp_path}", "systems=[wiener_hammerstein]"],
                              "place_data"))
    placed = tmp_path / "WienerHammerBenchMark" / "WienerHammerBenchMark.mat"
    assert placed.is_file()
    capsys.readouterr()
    place_data(compose_config([f"source={SHARED_DATA}", f"data_dir={tmp_path}", "systems=[wiener_hammerstein]"],
                              "place_data"))
    assert capsys.readouterr().out == f"kept    {placed}\n"
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError) as refused:
        place_data(compose_config([f"source={empty}", f"data_dir={tmp_path}", "systems=[silverbox]", "download=false"],
                                  "place_data"))
    assert str(refused.value) == (
        f"silverbox: no file named SNLS80mV.mat under source={str(empty)!r}, and it is not downloaded "
        "(download=false); get it from https://www.nonlinearbenchmark.org/benchmarks/silverbox and run again with "
        "source=<its folder>")
    assert placed.is_file() and not (tmp_path / "Silverbox").exists()


def test_process_noise_records_of_the_wrong_shape_are_refused_with_the_file_named(tmp_path, cache):
    folder = tmp_path / "wh_process_noise"
    folder.mkdir()
    np.savez(folder / "WH_EstimationExample.npz", u=np.zeros((8192, 10)), y=np.zeros((8192, 9)))
    np.savez(folder / "WH_TestDataset.npz", u=np.zeros((16384, 2)), y=np.zeros((16384, 2)))
    with pytest.raises(ConfigError, match=r"WH_EstimationExample.npz holds u \(8192, 10\) and y \(8192, 9\)"):
        load_benchmark(io_system("wiener_hammerstein_process_noise", data_dir=str(tmp_path)), cache)
    (folder / "WH_EstimationExample.npz").write_bytes(b"not an npz file")
    with pytest.raises(ConfigError, match=r"cannot read u and y of .*WH_EstimationExample\.npz"):
        load_benchmark(io_system("wiener_hammerstein_process_noise", data_dir=str(tmp_path)), cache)


def write_wh_file(data_dir: Path, u, y) -> None:
    folder = data_dir / "WienerHammerBenchMark"
    folder.mkdir(parents=True)
    scipy.io.savemat(folder / "WienerHammerBenchMark.mat", {"uBenchMark": u, "yBenchMark": y, "fs": 51200})


def test_missing_files_get_our_message_not_a_download(tmp_path, cache):
    with pytest.raises(ConfigError, match=r"WienerHammerBenchMark.mat is missing; place the benchmark's files "
                                          r"under data_dir="):
        load_benchmark(io_system("wiener_hammerstein", data_dir=str(tmp_path)), cache)
    assert not any(tmp_path.iterdir())  # the loader never ran (it would create its folder to download into)


@pytest.mark.parametrize(("content", "message"), [
    ("garbage", "cannot read .*WienerHammerBenchMark.mat"),
    ("nan", "holds 3 NaN or infinite values in its training record"),
    ("lengths", "cannot read .*WienerHammerBenchMark.mat .AssertionError: input sequence u need to have the same"),
    ("short", "the training record of .*WienerHammerBenchMark.mat has 0 samples, fewer than system.train_samples"),
])
def test_malformed_files_are_refused_with_the_file_named(content, message, tmp_path, cache):
    n = 188_000
    rng = np.random.default_rng(0)
    u, y = rng.standard_normal((n, 1)), rng.standard_normal((n, 1))
    if content == "garbage":
        (tmp_path / "WienerHammerBenchMark").mkdir()
        (tmp_path / "WienerHammerBenchMark" / "WienerHammerBenchMark.mat").write_bytes(b"not a mat file" * 100)
    else:
        if content == "nan":
            y[[6000, 7000, 8000]] = np.nan
        elif content == "lengths":
            y = y[:-10]
        else:
            u, y = u[:1000], y[:1000]
        write_wh_file(tmp_path, u, y)
    with pytest.raises(ConfigError, match=message):
        load_benchmark(io_system("wiener_hammerstein", data_dir=str(tmp_path)), cache)


def test_a_training_record_shorter_than_the_pool_is_refused(cache):
    system = io_system("wiener_hammerstein_sim")
    cfg = dataclasses.replace(system, samples={**(system.samples or {}), "train": 50_000})
    with pytest.raises(ConfigError, match=r"training record has 50,000 samples, fewer than system\.train_samples"):
        load_benchmark(cfg, cache)
