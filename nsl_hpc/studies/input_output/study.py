"""The input-output study: NARX and SUBNET models identified from input-output records (Silverbox,
Wiener-Hammerstein, or their simulated stand-ins), trained in lockstep (``lockstep``) and scored on every test record
(``scoring``).

Sizes are drawn from the task's grid coordinates: n_l (training prefix length) an integer in
[n_l~/2, n_l~], n_h an integer in [n_h~/2, n_h~]; n_d = depth. The draws, the initial weights and the batch
order depend on every coordinate (``draws: per_task``, Algorithm 2), or on all but the iteration multiplier m
(``shared_across_epochs``: tasks that differ only in m train the same model on the same data for longer);
n_i = m n_l iterations of B windows. Compute c = p n_i B (NARX) or p n_i B T (SUBNET,
whose p leaves out the encoder); data = n_l; model size = p.

The models and the training code (torch: ~1.5 s to import) are imported by the functions that build or train a
model, so that the commands that only read or check a sweep (status, merge, clean, resubmit) start without them.
"""

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from nsl_hpc.config.arch import Arch, NarxSettings, SubnetSettings
from nsl_hpc.config.schema import setting
from nsl_hpc.config.system import FileRecords, InputOutputSystem, MeasuredSource
from nsl_hpc.config.targets import labelled, located
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.checkpoint import Checkpointer, scoring_progress, trained_before
from nsl_hpc.core.errors import ConfigError, require_member
from nsl_hpc.studies.base import Pair, Study, Task, draw_tier
from nsl_hpc.studies.input_output.data import Benchmark, load_benchmark, read_files, require_files
from nsl_hpc.studies.settings import InputOutputTrain

if TYPE_CHECKING:
    from nsl_hpc.models.narx import NARX
    from nsl_hpc.models.subnet import SUBNET
    from nsl_hpc.studies.input_output.lockstep import IOMember


@dataclass(frozen=True)
class InputOutputPair(Pair):
    """An input-output (system, arch)'s settings (its data tiers are the system's)."""

    system: InputOutputSystem = setting("the records and their split")
    train: InputOutputTrain = setting("how each model trains")


def build_io_model(arch: Arch, system: InputOutputSystem, width: int, depth: int) -> "NARX | SUBNET":
    """The architecture ``arch._target_`` builds (NARX or SUBNET: the models the input-output lockstep training
    stacks) with n_h = width, n_d = depth."""
    return built_io_model(arch, subnet_state_dim(arch, system), width, depth)


def built_io_model(arch: Arch, state_dim: int, width: int, depth: int) -> "NARX | SUBNET":
    """``build_io_model`` with SUBNET's n_x ``state_dim``."""
    from nsl_hpc.models.narx import NARX
    from nsl_hpc.models.subnet import SUBNET

    builder = located("arch", arch)
    if isinstance(arch, NarxSettings) and builder is NARX:
        return NARX(arch.past_outputs, arch.past_inputs, width, depth, arch.block, arch.bypass, arch.zero_bias)
    if isinstance(arch, SubnetSettings) and builder is SUBNET:
        return SUBNET(state_dim, arch.past, width, depth, arch.block, tuple(arch.bypass), arch.residual,
                      arch.zero_bias, arch.zero_f_output)
    raise ConfigError(f"{labelled('arch', arch)}: the input_output study trains the package's narx and subnet (its "
                      "lockstep paths); a model of your own is an input-state architecture (docs/own_study.md)")


def subnet_state_dim(arch: Arch, system: InputOutputSystem) -> int:
    """SUBNET's n_x: the arch's ``state_dim``, or the system's (``system.subnet.state_dim``) where that is null."""
    return (arch.state_dim if isinstance(arch, SubnetSettings) else None) or system.subnet.state_dim


PARAMETERS: dict[tuple, int] = {}  # (arch, n_x, n_h, n_d) -> model_parameters' answer, each built once


def model_parameters(arch: Arch, state_dim: int, width: int, depth: int) -> int:
    """p of one architecture (SUBNET without its encoder), built once per distinct shape."""
    key = (repr(arch), state_dim, width, depth)
    if key not in PARAMETERS:
        PARAMETERS[key] = built_io_model(arch, state_dim, width, depth).counted_parameters()
    return PARAMETERS[key]


def past_window(arch: Arch) -> int:
    """P: the samples before t a model reads (its regressors, or its encoder's window)."""
    if isinstance(arch, NarxSettings):
        return max(arch.past_outputs, arch.past_inputs)
    return arch.past if isinstance(arch, SubnetSettings) else 0


def horizon(pair: "InputOutputPair", train_points: int | None = None) -> int:
    """Simulated steps per training window: SUBNET's T (``system.subnet.horizon``), or, with
    ``arch.shorten_horizon``, the n_l - P steps a training prefix of ``train_points`` samples holds where that
    is fewer (its one window; None: T); 1 for NARX (one step ahead)."""
    if not isinstance(pair.arch, SubnetSettings):
        return 1
    steps = pair.system.subnet.horizon
    if train_points is None or not pair.arch.shorten_horizon:
        return steps
    return min(steps, train_points - past_window(pair.arch))


def training_memory_mb(pair: "InputOutputPair", width: int, depth: int) -> float:
    """Estimated memory (MB) one model's training iteration keeps for its backward pass: six (n_h,) tensors per
    hidden layer, per window of the batch, for every MLP evaluation (NARX: F once; SUBNET: f and h at each of
    its T steps), plus the NARX regressors. Measured: a lockstep group of 16 SUBNETs at n_h 32, n_d 3, T 150 holds
    2.6 GB, 165 MB each (estimate 177)."""
    batch, dtype_bytes = pair.train.batch_size, np.dtype(pair.train.dtype).itemsize
    if isinstance(pair.arch, NarxSettings):
        values = 6 * width * depth + past_window(pair.arch) + 2
    else:
        values = horizon(pair) * 2 * 6 * width * depth
    return dtype_bytes * batch * values / 2**20


VALIDATION = "validation"  # the record name of the validation split (the training record after the pool)


def learning_fields(scores: Mapping[str, float], score_on: str) -> dict[str, Any]:
    """A row's scores from a model's ``scores`` (``scoring.score_records``' columns): nmae, nmse, rmse_mv of the free
    run on ``score_on``; whether that run stayed finite and its output's spread over the measured one's; the mean
    predictor's nmae there; and the free run's nmae on the validation split (NaN where the system has none)."""
    run = f"free_run_{score_on}"
    return {**{metric: scores[f"{metric}_{run}"] for metric in ("nmae", "nmse", "rmse_mv")},
            "free_run_finite": bool(scores[f"finite_{run}"]), "output_spread": scores[f"spread_{run}"],
            "mean_predictor_nmae": scores[f"nmae_mean_predictor_{score_on}"],
            "validation_nmae": scores.get(f"nmae_free_run_{VALIDATION}", math.nan)}


class InputOutput(Study[InputOutputPair]):
    name = "input_output"
    axes = ("system", "arch", "seed", "iter_multiplier", "data_tier", "width_tier", "depth")
    length_axis = "iter_multiplier"
    lockstep = True
    pair_schema = InputOutputPair
    shared_keys = ("system", "arch", "train", "draws")

    def check_size(self, label: str, key: str, value: Any, pair: InputOutputPair) -> None:
        allowed = {"data_tier": pair.system.data_tiers, "width_tier": pair.tiers.width, "depth": pair.tiers.depth}
        if key in allowed:
            require_member(label, value, list(allowed[key]))

    def check_pair(self, pair: InputOutputPair) -> None:
        if isinstance(pair.system.source, FileRecords):
            read_files(pair.system)  # your own records: every file, column and length checked before any work
        elif isinstance(pair.system.source, MeasuredSource):
            require_files(pair.system.name, pair.system.source)

    def check_task(self, task: Mapping[str, Any], sizes: Mapping[str, Any], pair: InputOutputPair) -> None:
        system, arch = pair.system, pair.arch
        if task["data_tier"] > system.train_samples:
            raise ConfigError(f"data_tier={task['data_tier']} is larger than the training pool of {system.name} "
                              f"(system.train_samples={system.train_samples})")
        past, steps = past_window(arch), horizon(pair, sizes["train_points"])
        if past > system.init_samples:
            raise ConfigError(f"{arch.name} reads {past} past samples, more than the {system.init_samples} "
                              f"that initialise a test simulation (system.init_samples)")
        if steps < 1 or sizes["train_points"] < past + steps:
            shorten = " or arch.shorten_horizon=true" if isinstance(arch, SubnetSettings) else ""
            steps = max(steps, 1)
            raise ConfigError(f"the training subset (n_l={sizes['train_points']} samples, data_tier="
                              f"{task['data_tier']}) is shorter than one {arch.name} window of {past + steps} "
                              f"samples ({past} past + T={steps}); use a larger data_tier{shorten}")

    def prepare_data(self, pair: InputOutputPair) -> None:
        load_benchmark(pair.system, ArrayCache(pair.cache_dir))

    def draw(self, task: Mapping[str, Any], pair: InputOutputPair) -> dict[str, Any]:
        rng = self.draw_rng(task, pair.draws)
        points, width = draw_tier(rng, task["data_tier"]), draw_tier(rng, task["width_tier"])
        return {"train_points": points, "width": width,
                "params": model_parameters(pair.arch, subnet_state_dim(pair.arch, pair.system), width, task["depth"]),
                "train_memory_mb": training_memory_mb(pair, width, task["depth"])}

    def training_length(self, task: Mapping[str, Any], drawn: Mapping[str, Any],
                        pair: InputOutputPair) -> dict[str, Any]:
        iterations = task["iter_multiplier"] * drawn["train_points"]
        return {"steps": iterations,
                "flops": float(drawn["params"]) * iterations * pair.train.batch_size
                * horizon(pair, drawn["train_points"])}

    def train_and_score_group(self, tasks: Sequence[Task[InputOutputPair]], on_progress: Callable[[], None],
                              checkpoint: Checkpointer | None = None) -> list[dict[str, Any]]:
        """Train the tasks' models in lockstep (they share system, arch and depth) and score each on every test
        record: nmae, nmse and rmse_mv are the free-run scores on ``system.score_on``, the others extra columns
        (``scoring``). train_seconds is the training time (over every resume from ``checkpoint``) divided among the
        tasks; compiled: whether the step ran compiled (``compile``)."""
        from nsl_hpc.studies.input_output.lockstep import train_lockstep
        from nsl_hpc.studies.input_output.scoring import numpy_mlps, score_records
        from nsl_hpc.studies.training import StepCompiler

        pair = tasks[0].pair
        benchmark = load_benchmark(pair.system, ArrayCache(pair.cache_dir))
        members = [self.member(task, benchmark) for task in tasks]
        started = time.perf_counter()
        compiler = StepCompiler(tasks[0].compile == "always")  # auto is resolved by a sweep's planner
        nets, theta, outcomes = train_lockstep(members, pair.train, on_progress, checkpoint, compiler)
        train_seconds = (time.perf_counter() - started + trained_before(checkpoint)) / len(tasks)
        scoring_progress(checkpoint, on_progress)()  # a stop asked by now keeps the trained models
        init = pair.system.init_samples
        records = dict(benchmark.tests)
        if len(benchmark.validation) > init:
            records[VALIDATION] = benchmark.validation
        scores = score_records(members[0].model, numpy_mlps(nets, theta), [member.scaling for member in members],
                               records, init, pair.system.mv_per_unit)
        return [{**learning_fields(row, pair.system.score_on), **row,
                 "steps": outcome.steps, "horizon": member.horizon, "final_loss": outcome.final_loss,
                 "finite": outcome.finite, "train_seconds": train_seconds, "compiled": compiler.enabled}
                for row, outcome, member in zip(scores, outcomes, members, strict=True)]

    def member(self, task: Task[InputOutputPair], benchmark: Benchmark) -> "IOMember":
        """The task's initialised model and training prefix, ready for ``train_lockstep``."""
        import torch

        from nsl_hpc.studies.input_output.lockstep import IOMember
        from nsl_hpc.studies.input_output.training import SignalScaling

        pair, sizes = task.pair, task.sizes
        torch.manual_seed(self.seed_for("init", task.keys, pair.draws))
        model = build_io_model(pair.arch, pair.system, sizes["width"], task.coordinates["depth"])
        record = benchmark.train.head(sizes["train_points"])
        return IOMember(model, record, SignalScaling.fit(record), sizes["steps"],
                        self.seed_for("shuffle", task.keys, pair.draws), horizon(pair, sizes["train_points"]))
