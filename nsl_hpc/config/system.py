"""The typed owners of the ``system`` group (conf/system/<name>.yaml): an input-state system (a simulated ODE
built by its ``_target_``: its constants, initial states, multisine input, simulation and test set) or an
input-output one (measured records or their simulated stand-ins: the training pool, its data tiers, the test
records, SUBNET's state and horizon). ``config.schema`` checks them."""

from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.arch import STUDIES
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.errors import ConfigError, require_choice

MEASURED_KINDS = ("benchmark", "records", "files")  # read from files: a nonlinear_benchmarks loader, .npz records of
#   realisations, records of your own (.csv, .npz, .mat columns: FileRecords)
SIMULATED_KINDS = ("duffing", "wiener_hammerstein")  # the measured systems' simulated stand-ins


@dataclass(frozen=True)
class Multisine:
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
    input: Multisine = setting("the input signal")
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
class FileRecords:
    """Measured records of your own (``source.kind: files``): one input and one output column per file."""

    kind: str = setting("files", choices=("files",))
    data_dir: str = setting("the folder the files lie in (relative: to the working directory)")
    train: str = setting("the training record's file: its first train_samples train, the rest validates")
    test: dict[str, str] = setting("the test records' files, by name (the names of system.tests)", nonempty=True)
    u: str = setting("the input column: a .csv header name, or an .npz / .mat variable")
    y: str = setting("the output column")
    sample_time_s: float = setting("the sample time (s)", 0, low_open=True)
    time: str | None = setting("a column of sample times, checked to step by sample_time_s", default=None)


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
    source: dict[str, Any] = setting("where the records come from (kind: benchmark, records, files, "
                                     "duffing, wiener_hammerstein)", nonempty=True)
    tests: list[str] = setting("the test records, each scored", nonempty=True)
    score_on: str = setting("the record of the row's nmae, nmse and rmse_mv")
    train_samples: int = setting("the training pool: the first this many samples", 1)
    data_tiers: list[int] = setting("the grid's training prefix lengths", 1, nonempty=True)
    subnet: SubnetShape = setting("SUBNET's state and horizon")
    fs_hz: float | None = setting("a stand-in's sampling rate (Hz)", 0, low_open=True, default=None)
    excitation: dict[str, Any] | None = setting("a stand-in's multisine", default=None)
    output_noise_std: float | None = setting("a stand-in's output noise (V)", 0, default=None)
    samples: dict[str, int] | None = setting("a stand-in's train and test lengths", 1, default=None)

    def check(self) -> None:
        require_choice("system.source.kind", self.source.get("kind"), [*MEASURED_KINDS, *SIMULATED_KINDS])
        require_choice("system.score_on", self.score_on, self.tests)
        if self.source["kind"] == "files":
            records = typed(FileRecords, self.source, "system.source")
            if sorted(records.test) != sorted(self.tests):
                raise ConfigError(f"system.tests names {', '.join(self.tests)}; system.source.test holds "
                                  f"{', '.join(records.test)}")
        if self.source["kind"] in SIMULATED_KINDS:
            for key in ("fs_hz", "excitation", "output_noise_std", "samples"):
                if getattr(self, key) is None:
                    raise ConfigError(f"system.{key} is missing: a simulated system ({self.source['kind']}) "
                                      "needs it")
