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
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from omegaconf import DictConfig

from nsl_hpc.cache import ArrayCache
from nsl_hpc.checkpoint import Checkpointer, scoring_progress, trained_before
from nsl_hpc.config import plain
from nsl_hpc.config.arch import IO_ARCHITECTURES, Narx, Subnet, arch_settings
from nsl_hpc.config.system import MEASURED_KINDS, InputOutputSystem
from nsl_hpc.config.targets import located, where
from nsl_hpc.errors import ConfigError, require_member
from nsl_hpc.studies.base import Study, draw_tier
from nsl_hpc.studies.input_output.data import Benchmark, load_benchmark, read_files, require_files
from nsl_hpc.studies.settings import InputOutputTrain

if TYPE_CHECKING:
    from nsl_hpc.models.narx import NARX
    from nsl_hpc.models.subnet import SUBNET
    from nsl_hpc.studies.input_output.lockstep import IOMember


def build_io_model(arch_cfg: Mapping[str, Any], system_cfg: Mapping[str, Any], width: int, depth: int
                   ) -> "NARX | SUBNET":
    """The architecture ``arch_cfg._target_`` builds (NARX or SUBNET: the models the input-output lockstep
    training stacks) with n_h = width, n_d = depth."""
    from nsl_hpc.models.narx import NARX
    from nsl_hpc.models.subnet import SUBNET

    arch, builder = arch_settings(arch_cfg), located("arch", arch_cfg)
    if isinstance(arch, Narx) and builder is NARX:
        return NARX(arch.past_outputs, arch.past_inputs, width, depth, arch.block)
    if isinstance(arch, Subnet) and builder is SUBNET:
        return SUBNET(subnet_state_dim(arch_cfg, system_cfg), arch.past, width, depth, arch.block, tuple(arch.bypass),
                      arch.residual, arch.zero_bias, arch.zero_f_output)
    raise ConfigError(f"{where('arch', arch_cfg)}: arch._target_={arch_cfg.get('_target_')!r}: the input_output "
                      "study trains the package's narx and subnet (its lockstep paths); a model of your own is an "
                      "input-state architecture (docs/own_study.md)")


def subnet_state_dim(arch_cfg: Mapping[str, Any], system_cfg: Mapping[str, Any]) -> int:
    """SUBNET's n_x: the arch's ``state_dim``, or the system's (``system.subnet.state_dim``) where that is null."""
    return arch_cfg.get("state_dim") or system_cfg["subnet"]["state_dim"]


@cache
def model_parameters(arch_items: tuple, state_dim: int, width: int, depth: int) -> int:
    """p of one architecture (SUBNET without its encoder), built once per distinct shape."""
    arch = {key: list(value) if isinstance(value, tuple) else value for key, value in arch_items}
    return build_io_model(arch, {"subnet": {"state_dim": state_dim}}, width, depth).counted_parameters()


def past_window(arch_cfg: Mapping[str, Any]) -> int:
    """P: the samples before t a model reads (its regressors, or its encoder's window)."""
    if arch_cfg["name"] == "narx":
        return max(arch_cfg["past_outputs"], arch_cfg["past_inputs"])
    return arch_cfg["past"]


def horizon(base: Mapping[str, Any], train_points: int | None = None) -> int:
    """Simulated steps per training window: SUBNET's T (``system.subnet.horizon``), or, with
    ``arch.shorten_horizon``, the n_l - P steps a training prefix of ``train_points`` samples holds where that
    is fewer (its one window; None: T); 1 for NARX (one step ahead)."""
    if base["arch"]["name"] != "subnet":
        return 1
    steps = base["system"]["subnet"]["horizon"]
    if train_points is None or not base["arch"]["shorten_horizon"]:
        return steps
    return min(steps, train_points - past_window(base["arch"]))


def training_memory_mb(base: Mapping[str, Any], width: int, depth: int) -> float:
    """Estimated memory (MB) one model's training iteration keeps for its backward pass: six (n_h,) tensors per
    hidden layer, per window of the batch, for every MLP evaluation (NARX: F once; SUBNET: f and h at each of
    its T steps), plus the NARX regressors. Measured: a lockstep group of 16 SUBNETs at n_h 32, n_d 3, T 150 holds
    2.6 GB, 165 MB each (estimate 177)."""
    batch, dtype_bytes = base["train"]["batch_size"], np.dtype(base["train"]["dtype"]).itemsize
    if base["arch"]["name"] == "narx":
        values = 6 * width * depth + past_window(base["arch"]) + 2
    else:
        values = horizon(base) * 2 * 6 * width * depth
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


class InputOutput(Study):
    name = "input_output"
    axes = ("system", "arch", "seed", "iter_multiplier", "data_tier", "width_tier", "depth")
    length_axis = "iter_multiplier"
    lockstep = True
    settings_schemas = (("train", InputOutputTrain), ("system", InputOutputSystem))
    shared_keys = ("system", "arch", "train", "draws")
    rounding_only = (("train", "rollout_segment", {"feature_major": 10, "batch_major": 10}),)
    neutral = (("train", "schedule", dict.fromkeys(IO_ARCHITECTURES, "warmup_cosine")),)

    def shared_identity(self, values: Mapping[str, Any]) -> str:
        """``Study.shared_identity`` with the train group's per-architecture schedule reduced to the pair's own, left
        out where that is warmup_cosine, the schedule of every task before the setting: their ids stay."""
        train = dict(values["train"])
        own = dict(train.pop("schedule", {})).get(values["arch"]["name"], "warmup_cosine")
        if own != "warmup_cosine":
            train["schedule"] = own
        return super().shared_identity({**values, "train": train})

    def check_size(self, label: str, key: str, value: Any, base: Mapping[str, Any]) -> None:
        allowed = {"data_tier": base["system"]["data_tiers"], "width_tier": base["tiers"]["width"],
                   "depth": base["tiers"]["depth"]}
        if key in allowed:
            require_member(label, value, list(allowed[key]))

    def check_pair(self, base: Mapping[str, Any]) -> None:
        if base["system"]["source"]["kind"] == "files":
            read_files(base["system"])  # your own records: every file, column and length checked before any work
        elif base["system"]["source"]["kind"] in MEASURED_KINDS:
            require_files(base["system"]["name"], base["system"]["source"])

    def check_task(self, task: Mapping[str, Any], sizes: Mapping[str, Any], base: Mapping[str, Any]) -> None:
        system, arch = base["system"], base["arch"]
        if task["data_tier"] > system["train_samples"]:
            raise ConfigError(f"data_tier={task['data_tier']} is larger than the training pool of {system['name']} "
                              f"(system.train_samples={system['train_samples']})")
        past, steps = past_window(arch), horizon(base, sizes["train_points"])
        if past > system["init_samples"]:
            raise ConfigError(f"{arch['name']} reads {past} past samples, more than the {system['init_samples']} "
                              f"that initialise a test simulation (system.init_samples)")
        if steps < 1 or sizes["train_points"] < past + steps:
            shorten = " or arch.shorten_horizon=true" if arch["name"] == "subnet" else ""
            steps = max(steps, 1)
            raise ConfigError(f"the training subset (n_l={sizes['train_points']} samples, data_tier="
                              f"{task['data_tier']}) is shorter than one {arch['name']} window of {past + steps} "
                              f"samples ({past} past + T={steps}); use a larger data_tier{shorten}")

    def prepare_data(self, base: Mapping[str, Any]) -> None:
        load_benchmark(base["system"], ArrayCache(base["cache_dir"]))

    def draw(self, task: Mapping[str, Any], base: Mapping[str, Any]) -> dict[str, Any]:
        rng = self.draw_rng(task, base["draws"])
        points, width = draw_tier(rng, task["data_tier"]), draw_tier(rng, task["width_tier"])
        arch_items = tuple((key, tuple(value) if isinstance(value, list) else value)
                           for key, value in base["arch"].items())
        return {"train_points": points, "width": width,
                "params": model_parameters(arch_items, subnet_state_dim(base["arch"], base["system"]), width,
                                           task["depth"]),
                "train_memory_mb": training_memory_mb(base, width, task["depth"])}

    def training_length(self, task: Mapping[str, Any], drawn: Mapping[str, Any],
                        base: Mapping[str, Any]) -> dict[str, Any]:
        iterations = task["iter_multiplier"] * drawn["train_points"]
        return {"steps": iterations,
                "flops": float(drawn["params"]) * iterations * base["train"]["batch_size"]
                * horizon(base, drawn["train_points"])}

    def train_and_score_group(self, items: Sequence[tuple[DictConfig, Mapping[str, Any], Mapping[str, Any]]],
                             on_progress: Callable[[], None], checkpoint: Checkpointer | None = None
                             ) -> list[dict[str, Any]]:
        """Train the items' models in lockstep (they share system, arch and depth) and score each on every test
        record: nmae, nmse and rmse_mv are the free-run scores on ``system.score_on``, the others extra columns
        (``scoring``). train_seconds is the training time (over every resume from ``checkpoint``) divided among the
        items; compiled: whether the step ran compiled (``compile``)."""
        from nsl_hpc.studies.input_output.lockstep import train_lockstep
        from nsl_hpc.studies.input_output.scoring import numpy_mlps, score_records
        from nsl_hpc.studies.training import StepCompiler

        cfg = items[0][0]
        system_cfg = plain(cfg.system)
        benchmark = load_benchmark(system_cfg, ArrayCache(cfg.cache_dir))
        members = [self.member(item_cfg, task, sizes, system_cfg, benchmark) for item_cfg, task, sizes in items]
        started = time.perf_counter()
        compiler = StepCompiler(cfg.get("compile") == "always")  # auto is resolved by a sweep's planner
        nets, theta, outcomes = train_lockstep(members, plain(cfg.train, resolve=False), on_progress, checkpoint,
                                               compiler)
        train_seconds = (time.perf_counter() - started + trained_before(checkpoint)) / len(items)
        scoring_progress(checkpoint, on_progress)()  # a stop asked by now keeps the trained models
        init = system_cfg["init_samples"]
        records = dict(benchmark.tests)
        if len(benchmark.validation) > init:
            records[VALIDATION] = benchmark.validation
        scores = score_records(members[0].model, numpy_mlps(nets, theta), [member.scaling for member in members],
                               records, init, system_cfg["mv_per_unit"])
        return [{**learning_fields(row, system_cfg["score_on"]), **row,
                 "steps": outcome.steps, "horizon": member.horizon, "final_loss": outcome.final_loss,
                 "finite": outcome.finite, "train_seconds": train_seconds, "compiled": compiler.enabled}
                for row, outcome, member in zip(scores, outcomes, members, strict=True)]

    def member(self, cfg: DictConfig, task: Mapping[str, Any], sizes: Mapping[str, Any],
               system_cfg: Mapping[str, Any], benchmark: Benchmark) -> "IOMember":
        """The task's initialised model and training prefix, ready for ``train_lockstep``."""
        import torch

        from nsl_hpc.studies.input_output.lockstep import IOMember
        from nsl_hpc.studies.input_output.training import SignalScaling

        torch.manual_seed(self.seed_for("init", task, cfg.draws))
        model = build_io_model(cfg.arch, system_cfg, sizes["width"], task["depth"])
        record = benchmark.train.head(sizes["train_points"])
        return IOMember(model, record, SignalScaling.fit(record), sizes["steps"],
                        self.seed_for("shuffle", task, cfg.draws),
                        horizon({"system": system_cfg, "arch": cfg.arch}, sizes["train_points"]))
