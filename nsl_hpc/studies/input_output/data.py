"""Input-output signals of the input-output study: the measured benchmarks (Silverbox, Wiener-Hammerstein 2009),
read with the standard ``nonlinear_benchmarks`` loaders from ``data_dir`` (``system.source.data_dir``), the
Wiener-Hammerstein benchmark with process noise, read from its records (.npz, one column per realisation), records
of your own (``source.kind: files``: a column each of .csv, .npz or .mat files), or simulated stand-ins, and their
split into training pool, validation and test records.

A task trains on the prefix u_1..u_{n_l}, y_1..y_{n_l} of the training pool (the first ``train_samples``
samples of the benchmark's training record); the rest of that record is the validation split, kept out of
training and not used for selection. Every test record of the benchmark (``system.tests``) is scored.
"""

import contextlib
import dataclasses
import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nsl_hpc.config.system import (
    BenchmarkSource,
    FileRecords,
    InputOutputSystem,
    MeasuredSource,
    RecordsSource,
    SimulatedSource,
)
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.errors import ConfigError, one_line
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.systems.duffing import simulate_duffing
from nsl_hpc.systems.wiener_hammerstein import simulate_wiener_hammerstein

# Bump when the stand-in simulations change results, so cached records are not reused.
STANDIN_VERSION = 1


@dataclass(frozen=True)
class Signals:
    """One single-input single-output record; both arrays (N,), float64, in the benchmark's units (V)."""

    u: np.ndarray
    y: np.ndarray

    def __len__(self) -> int:
        return len(self.y)

    def head(self, samples: int) -> "Signals":
        return Signals(self.u[:samples], self.y[:samples])


@dataclass(frozen=True)
class Benchmark:
    train: Signals  # the training pool: a task trains on its first n_l samples
    validation: Signals  # the rest of the training record, never trained on
    tests: dict[str, Signals]  # the test records by name (system.tests); scored after their first init_samples


def load_benchmark(system: InputOutputSystem, cache: ArrayCache) -> Benchmark:
    """The records of an input-output system (measured or simulated), split as configured."""
    source = system.source
    if isinstance(source, BenchmarkSource):
        train, tests = read_measured(system.name, source, system.tests)
        origin = f" of {measured_file(source)}"
    elif isinstance(source, RecordsSource):
        train, tests = read_records(system.name, source, system.tests)
        origin = f" of {Path(source.data_dir) / source.train.file}"
    elif isinstance(source, FileRecords):
        train, tests = read_files(system)
        origin = f" of {Path(source.data_dir) / source.train}"
    else:
        train, tests = simulated_signals(system, cache)
        origin = ""
    pool = system.train_samples
    if len(train) < pool:
        raise ConfigError(f"{system.name}: the training record{origin} has {len(train):,} samples, fewer "
                          f"than system.train_samples={pool:,} (the largest data tier)")
    return Benchmark(train.head(pool), Signals(train.u[pool:], train.y[pool:]), tests)


def read_measured(name: str, source: BenchmarkSource, names: list[str]) -> tuple[Signals, dict[str, Signals]]:
    """Training record and test records (named ``names``, in the loader's order) read by
    ``nonlinear_benchmarks.<loader>(dir_placement=data_dir)``; the files are checked first, so a missing copy
    is our one-line error, never a download attempt."""
    import nonlinear_benchmarks  # imported here: only tasks on measured data need it

    require_files(name, source)
    data_dir = Path(source.data_dir)
    loader = getattr(nonlinear_benchmarks, source.loader)
    data_file = measured_file(source)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            (train,), tests = loader(dir_placement=str(data_dir), always_return_tuples_of_datasets=True)
    except Exception as error:
        raise ConfigError(f"{name}: cannot read {data_file} ({type(error).__name__}: {error}); replace it with "
                          "an intact copy of the benchmark file") from None
    if len(tests) != len(names):
        raise ConfigError(f"{name}: {data_file} holds {len(tests)} test records, system.tests names {len(names)} "
                          f"({', '.join(names)})")
    return (checked_signals(name, data_file, "training", train.u, train.y),
            {test_name: checked_signals(name, data_file, f"{test_name} test", test.u, test.y)
             for test_name, test in zip(names, tests, strict=True)})


def read_records(name: str, source: RecordsSource, names: list[str]) -> tuple[Signals, dict[str, Signals]]:
    """Training record and test records (``names``) from .npz files of u and y arrays, (samples, realisations):
    the training record is ``source.train``'s realisations (``columns``) one after another; each test record one
    column of ``source.test.file`` (``source.test.columns``: name -> column)."""
    require_files(name, source)
    if sorted(names) != sorted(source.test.columns):
        raise ConfigError(f"{name}: system.tests names {', '.join(names)}; source.test.columns holds "
                          f"{', '.join(source.test.columns)}")
    train_file = Path(source.data_dir) / source.train.file
    u, y = record_columns(name, train_file)
    train = checked_signals(name, train_file, "training", u[:, source.train.columns].T.ravel(),
                            y[:, source.train.columns].T.ravel())
    test_file = Path(source.data_dir) / source.test.file
    u, y = record_columns(name, test_file)
    return train, {test: checked_signals(name, test_file, f"{test} test", u[:, source.test.columns[test]],
                                         y[:, source.test.columns[test]]) for test in names}


def record_columns(name: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The u and y arrays of an .npz file of records, (samples, realisations) each."""
    try:
        with np.load(path) as arrays:
            u, y = np.asarray(arrays["u"], dtype=float), np.asarray(arrays["y"], dtype=float)
    except (OSError, ValueError, KeyError) as error:
        raise ConfigError(f"{name}: cannot read u and y of {path} ({type(error).__name__}: {error}); replace it "
                          "with an intact copy") from None
    if u.ndim != 2 or u.shape != y.shape:
        raise ConfigError(f"{name}: {path} holds u {u.shape} and y {y.shape}; expected two equal (samples, "
                          "realisations) arrays")
    return u, y


def read_files(system: InputOutputSystem) -> tuple[Signals, dict[str, Signals]]:
    """Training record and test records of ``source.kind: files`` (``config.system.FileRecords``): the columns
    ``source.u`` and ``source.y`` of each file, refused in one line where a file, a column or a length is wrong or
    the time column does not step by ``source.sample_time_s``."""
    name, source = system.name, system.source
    assert isinstance(source, FileRecords)
    require_files(name, source)
    files = {"training": source.train, **{f"{test} test": file for test, file in source.test.items()}}
    records = {part: file_record(name, source, Path(source.data_dir) / file, part) for part, file in files.items()}
    for test in source.test:
        if len(records[f"{test} test"]) <= system.init_samples:
            raise ConfigError(f"{name}: the {test} test record ({source.test[test]}) has "
                              f"{len(records[f'{test} test'])} samples, not more than the system.init_samples="
                              f"{system.init_samples} that initialise its simulation")
    return records.pop("training"), {test: records[f"{test} test"] for test in system.tests}


def file_record(name: str, source: FileRecords, path: Path, part: str) -> Signals:
    """The u and y columns of one file (.csv with a header line, .npz, .mat), checked."""
    columns = file_columns(name, path)
    wanted = [source.u, source.y, *([source.time] if source.time else [])]
    for column in wanted:
        if column not in columns:
            raise ConfigError(f"{name}: {path} has no column {column!r} (system.source.u, .y, .time); it has: "
                              f"{', '.join(columns)}")
    if source.time:
        steps = np.diff(np.ravel(columns[source.time]))
        if len(steps) and not np.allclose(steps, source.sample_time_s, rtol=1e-6, atol=0):
            raise ConfigError(f"{name}: {path} column {source.time!r} steps by {np.min(steps):g}..{np.max(steps):g}"
                              f" s, not system.source.sample_time_s={source.sample_time_s:g}")
    return checked_signals(name, path, part, np.ravel(columns[source.u]), np.ravel(columns[source.y]))


def file_columns(name: str, path: Path) -> dict[str, np.ndarray]:
    """Every column of a .csv (its header names them), .npz or .mat file (its variables), by name."""
    try:
        if path.suffix == ".csv":
            table = np.genfromtxt(path, delimiter=",", names=True, dtype=float, encoding="utf-8")
            return {column: np.asarray(table[column]) for column in table.dtype.names or ()}
        if path.suffix == ".npz":
            with np.load(path) as arrays:
                return {key: np.asarray(arrays[key], dtype=float) for key in arrays.files}
        if path.suffix == ".mat":
            from scipy.io import loadmat

            return {key: np.asarray(value, dtype=float) for key, value in loadmat(path).items()
                    if not key.startswith("__")}
    except (OSError, ValueError, TypeError) as error:
        raise ConfigError(f"{name}: cannot read {path} ({type(error).__name__}: "
                          f"{one_line(error)[:160]}); replace it with an intact copy") from None
    raise ConfigError(f"{name}: {path} is no .csv, .npz or .mat file")


def require_files(name: str, source: MeasuredSource) -> None:
    """Raise ConfigError naming the first of a source's files (``paths``) missing under ``source.data_dir``."""
    data_dir = Path(source.data_dir)
    files = source.paths()
    for relative in files:
        if not (data_dir / relative).is_file():
            where = (f"system.source.data_dir={str(data_dir)!r} holds no {relative} (relative: to the working "
                     "directory)" if isinstance(source, FileRecords) else
                     f"place the benchmark's files under data_dir={str(data_dir)!r} as {', '.join(files)} (python -m "
                     "nsl_hpc.place_data; docs/science.md, 'The input-output study')")
            raise ConfigError(f"{name}: data file {data_dir / relative} is missing; {where}")


def measured_file(source: BenchmarkSource) -> Path:
    """The file the loader reads (the last of ``source.files``)."""
    return Path(source.data_dir) / source.files[-1]


def checked_signals(name: str, data_file: Path, part: str, u: Any, y: Any) -> Signals:
    """u and y as a Signals, refused unless both are finite, one-dimensional and of equal length."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    if u.ndim != 1 or u.shape != y.shape:
        raise ConfigError(f"{name}: {data_file} holds a {part} record of shapes u {u.shape}, y {y.shape}; expected "
                          "two equally long one-dimensional signals")
    if not (np.isfinite(u).all() and np.isfinite(y).all()):
        bad = int((~np.isfinite(u)).sum() + (~np.isfinite(y)).sum())
        raise ConfigError(f"{name}: {data_file} holds {bad} NaN or infinite values in its {part} record")
    return Signals(u, y)


def simulated_signals(system: InputOutputSystem, cache: ArrayCache) -> tuple[Signals, dict[str, Signals]]:
    """Training record and test records (``system.tests``) of a stand-in, simulated once per configuration and
    then read from cache."""
    key = {"version": STANDIN_VERSION, "system": dataclasses.asdict(system)}
    parts = ["train", *system.tests]

    def create() -> dict[str, np.ndarray]:
        arrays = {}
        for part in parts:
            record = simulate_signals(system, part)
            arrays[f"{part}_u"], arrays[f"{part}_y"] = record.u, record.y
        return arrays

    arrays = cache.get_or_create(key, create)
    records = {part: Signals(arrays[f"{part}_u"], arrays[f"{part}_y"]) for part in parts}
    return records.pop("train"), records


def simulate_signals(system: InputOutputSystem, part: str) -> Signals:
    """One record of a stand-in: its own input realisation, the simulated output plus white noise."""
    source = system.source
    assert isinstance(source, SimulatedSource) and system.samples and system.excitation and system.fs_hz
    samples = system.samples[part]
    rng = np.random.default_rng(stable_seed("record", system.name, source.seed, part))
    u = random_phase_multisine(rng, samples, system.fs_hz, system.excitation.band_hz, system.excitation.rms)
    simulators: dict[str, Callable[..., np.ndarray]] = {"duffing": simulate_duffing,
                                                      "wiener_hammerstein": simulate_wiener_hammerstein}
    y = simulators[source.kind](u, system.fs_hz, **source.params)
    return Signals(u, y + (system.output_noise_std or 0.0) * rng.standard_normal(samples))


def random_phase_multisine(rng: np.random.Generator, samples: int, fs_hz: float, band_hz: list[float],
                           rms: float) -> np.ndarray:
    """(samples,) one period of a multisine with equal amplitudes on every frequency bin in (band_hz[0],
    band_hz[1]] and uniformly random phases, scaled to ``rms``."""
    frequencies = np.fft.rfftfreq(samples, d=1.0 / fs_hz)
    excited = (frequencies > band_hz[0]) & (frequencies <= band_hz[1])
    if not excited.any():
        raise ConfigError(f"excitation band {band_hz} Hz holds no frequency bin of a {samples}-sample record")
    spectrum = np.where(excited, np.exp(2j * math.pi * rng.uniform(size=len(frequencies))), 0.0)
    signal = np.fft.irfft(spectrum, n=samples)
    return signal * rms / np.sqrt(np.mean(signal**2))
