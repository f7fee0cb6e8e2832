"""The typed owners of the ``system`` group (conf/system/<name>.yaml): an input-state system (a simulated ODE
built by its ``_target_``: its constants, initial states, multisine input, simulation and test set) or an
input-output one (measured records or their simulated stand-ins: the training pool, its data tiers, the test
records, SUBNET's state and horizon). ``config.schema`` checks them."""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.arch import STUDIES
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.core.errors import ConfigError, require_choice

MEASURED_KINDS = ("benchmark", "records", "files")  # read from files: a nonlinear_benchmarks loader, .npz records of
#   realisations, records of your own (.csv, .npz, .mat columns: FileRecords)
SIMULATED_KINDS = ("duffing", "wiener_hammerstein")  # the measured systems' simulated stand-ins


@dataclass(frozen=True)
class MultisineSettings:
    """The input: a random-phase multisine per input channel."""

    amplitude: float = setting("peak amplitude", 0, low_open=True)
    f0_hz: float = setting("frequency of the first harmonic's spacing (Hz)", 0, low_open=True)
    harmonics: int = setting("harmonics summed", 1)
    first_harmonic: int = setting("the lowest harmonic", 1)


@dataclass(frozen=True)
class Simulation:
    """How trajectories are simulated."""

    duration_s: float = setting("length of a trajectory (s)", 0, low_open=True)
    dt_s: float = setting("sample spacing (s)", 0, low_open=True)
    rtol: float = setting("the ODE solver's relative tolerance", 0, low_open=True)
    atol: float = setting("the ODE solver's absolute tolerance", 0, low_open=True)


@dataclass(frozen=True)
class TestSet:
    """The system's test set (conf/test_set/)."""

    trajectories: int = setting("trajectories", 1)
    duration_s: float = setting("length of each (s)", 0, low_open=True)
    seed: int = setting("their own seed, disjoint from every training pool", 0)


@dataclass(frozen=True)
class InputStateSystem:
    """A simulated system of the input-state study (the package's port-Hamiltonian ones, or one of yours)."""

    name: str = setting("the system")
    _target_: str = setting("the class or function that builds it from params (nsl_hpc.systems.System)")
    study: str = setting("its study", choices=STUDIES)
    params: dict[str, Any] = setting("the constants (keyword arguments of _target_)")
    initial_box: list[list[float]] = setting("uniform initial state: [low, high] per state", nonempty=True)
    input: MultisineSettings = setting("the input signal")
    simulation: Simulation = setting("the simulation")
    test_set: TestSet = setting("the test set")
    constants: str | None = setting("which of variants the params are", default=None)
    variants: dict[str, Any] | None = setting("named sets of constants", default=None)

    def check(self) -> None:
        for state, bounds in enumerate(self.initial_box):
            if len(bounds) != 2 or bounds[0] > bounds[1]:
                raise ConfigError(f"system.initial_box[{state}]={bounds!r} must be [low, high]")
        if self.simulation.dt_s > self.simulation.duration_s:
            raise ConfigError(f"system.simulation.dt_s={self.simulation.dt_s} is longer than its duration_s="
                              f"{self.simulation.duration_s}")


@dataclass(frozen=True)
class Source:
    """Where an input-output system's records come from: ``kind`` says which of the forms below."""

    kind: str = setting("benchmark, records or files (measured), duffing or wiener_hammerstein (a stand-in)",
                        choices=(*MEASURED_KINDS, *SIMULATED_KINDS))

    @classmethod
    def from_values(cls, values: Any, key: str) -> "Source":
        """The ``system.source`` group ``key`` typed by the form its ``kind`` names."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{key}={values!r} must be a group of keys, kind first")
        require_choice(f"{key}.kind", values.get("kind"), [*MEASURED_KINDS, *SIMULATED_KINDS])
        return typed(SOURCES[values["kind"]], values, key)


@dataclass(frozen=True)
class MeasuredSource(Source):
    """Measured records in files under ``data_dir``."""

    data_dir: str = setting("the folder the files lie in (relative: to the working directory)")

    def paths(self) -> list[str]:
        """The files it reads, relative to data_dir."""
        raise NotImplementedError


@dataclass(frozen=True)
class BenchmarkSource(MeasuredSource):
    """A benchmark read by its ``nonlinear_benchmarks`` loader (``kind: benchmark``)."""

    loader: str = setting("the nonlinear_benchmarks loader, e.g. Silverbox")
    files: list[str] = setting("the benchmark's files (the loader reads the last)", nonempty=True)

    def paths(self) -> list[str]:
        return list(self.files)


@dataclass(frozen=True)
class TrainColumns:
    """The training record of .npz records: realisations one after another."""

    file: str = setting("the .npz file of u and y, (samples, realisations)")
    columns: list[int] = setting("the realisations it trains on", 0, nonempty=True)


@dataclass(frozen=True)
class TestColumns:
    """The test records of .npz records: one realisation each."""

    file: str = setting("the .npz file of u and y, (samples, realisations)")
    columns: dict[str, int] = setting("test record name -> its realisation", 0, nonempty=True)


@dataclass(frozen=True)
class RecordsSource(MeasuredSource):
    """Realisations in .npz files of u and y (``kind: records``)."""

    files: list[str] = setting("the files", nonempty=True)
    train: TrainColumns = setting("the training record")
    test: TestColumns = setting("the test records")

    def paths(self) -> list[str]:
        return list(self.files)


@dataclass(frozen=True)
class FileRecords(MeasuredSource):
    """Measured records of your own (``source.kind: files``): one input and one output column per file."""

    train: str = setting("the training record's file: its first train_samples train, the rest validates")
    test: dict[str, str] = setting("the test records' files, by name (the names of system.tests)", nonempty=True)
    u: str = setting("the input column: a .csv header name, or an .npz / .mat variable")
    y: str = setting("the output column")
    sample_time_s: float = setting("the sample time (s)", 0, low_open=True)
    time: str | None = setting("a column of sample times, checked to step by sample_time_s", default=None)

    def paths(self) -> list[str]:
        return [self.train, *self.test.values()]


@dataclass(frozen=True)
class SimulatedSource(Source):
    """A measured system's simulated stand-in (``kind: duffing, wiener_hammerstein``)."""

    params: dict[str, Any] = setting("the simulation's constants")
    seed: int = setting("the seed of its input and noise realisations", 0)


SOURCES: dict[str, type[Source]] = {"benchmark": BenchmarkSource, "records": RecordsSource, "files": FileRecords,
                                    **dict.fromkeys(SIMULATED_KINDS, SimulatedSource)}


@dataclass(frozen=True)
class Excitation:
    """A stand-in's input: a random-phase multisine."""

    band_hz: list[float] = setting("the excited band [low, high] (Hz)", 0, nonempty=True)
    rms: float = setting("its RMS (V)", 0, low_open=True)


@dataclass(frozen=True)
class SubnetShape:
    """SUBNET on this system."""

    state_dim: int = setting("n_x", 1)
    horizon: int = setting("T: simulated steps per training sub-sequence", 1)


@dataclass(frozen=True)
class InputOutputSystem:
    """A system of the input-output study: measured records or a simulated stand-in."""

    name: str = setting("the system")
    study: str = setting("its study", choices=STUDIES)
    init_samples: int = setting("the first test samples initialise a simulation; the error counts the rest", 0)
    mv_per_unit: float = setting("RMSE is also reported in mV", 0, low_open=True)
    source: Source = setting("where the records come from")
    tests: list[str] = setting("the test records, each scored", nonempty=True)
    score_on: str = setting("the record of the row's nmae, nmse and rmse_mv")
    train_samples: int = setting("the training pool: the first this many samples", 1)
    data_tiers: list[int] = setting("the grid's training prefix lengths", 1, nonempty=True)
    subnet: SubnetShape = setting("SUBNET's state and horizon")
    fs_hz: float | None = setting("a stand-in's sampling rate (Hz)", 0, low_open=True, default=None)
    excitation: Excitation | None = setting("a stand-in's multisine", default=None)
    output_noise_std: float | None = setting("a stand-in's output noise (V)", 0, default=None)
    samples: dict[str, int] | None = setting("a stand-in's train and test lengths", 1, default=None)

    def check(self) -> None:
        require_choice("system.score_on", self.score_on, self.tests)
        if isinstance(self.source, FileRecords) and sorted(self.source.test) != sorted(self.tests):
            raise ConfigError(f"system.tests names {', '.join(self.tests)}; system.source.test holds "
                              f"{', '.join(self.source.test)}")
        if isinstance(self.source, SimulatedSource):
            for key in ("fs_hz", "excitation", "output_noise_std", "samples"):
                if getattr(self, key) is None:
                    raise ConfigError(f"system.{key} is missing: a simulated system ({self.source.kind}) needs it")
