"""The input-state study: models of dx/dt and y from (x, u) samples of simulated port-Hamiltonian systems.

Sizes are drawn from the task's grid coordinates: d uniform in [d~/2, d~], n_t = d / 10 trajectories,
n_h an integer in [n_h~/2, n_h~], n_d an integer in [n_d~/2, n_d~]. The draws, the initial weights and the
batch order depend on every coordinate (``draws: per_task``, Algorithm 1), or on all but the epoch count
(``shared_across_epochs``: tasks that differ only in n_e train the same model on the same data for longer).
Compute c = p n_e N (flops column; N training points), data = N, model size = p.

The models and the training code (torch: ~1.5 s to import) are imported by the functions that build or train a
model, so that the commands that only read or check a sweep (status, merge, clean, resubmit) start without them.
"""

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from nsl_hpc.config.arch import Arch
from nsl_hpc.config.schema import setting
from nsl_hpc.config.system import InputStateSystem
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.checkpoint import Checkpointer, scoring_progress, trained_before
from nsl_hpc.core.errors import ConfigError, require_member
from nsl_hpc.studies.base import Pair, Study, Task, Tiers, draw_tier, model_of
from nsl_hpc.studies.input_state.data import build_test_set, build_training_set, points_per_trajectory, training_points
from nsl_hpc.studies.settings import InputStateTrain, Metric, batch_count
from nsl_hpc.systems import build_system, check_system

if TYPE_CHECKING:
    from nsl_hpc.studies.input_state.lockstep import Member


@dataclass(frozen=True)
class InputStateTiers(Tiers):
    """The input-state grid's tiers, its data tiers among them."""

    data: list[int] = setting("d~ values", 1, nonempty=True)


@dataclass(frozen=True)
class InputStatePair(Pair):
    """An input-state (system, arch)'s settings."""

    system: InputStateSystem = setting("the simulated system")
    train: InputStateTrain = setting("how each model trains")
    metric: Metric = setting("how the errors are normalised")
    data_per_trajectory: float = setting("n_t = d / this trajectories", 0, low_open=True)
    tiers: InputStateTiers = setting("the allowed tiers")


TIER_OF = {"data_tier": "data", "width_tier": "width", "depth_tier": "depth"}


DIMENSIONS: dict[str, tuple[int, int]] = {}  # a system's target and constants -> (n, m), each built once


def system_dimensions(settings: InputStateSystem) -> tuple[int, int]:
    """(n, m): the state and input sizes of the system ``settings`` builds."""
    identity = f"{settings._target_}{settings.params!r}"
    if identity not in DIMENSIONS:
        system = build_system(settings)
        DIMENSIONS[identity] = (system.state_dim, system.input_dim)
    return DIMENSIONS[identity]


SHAPES: dict[tuple, tuple[int, bool]] = {}  # (arch, n, m, n_h, n_d) -> model_shape's answer, each built once


def model_shape(arch: Arch, dimensions: tuple[int, int], width: int, depth: int) -> tuple[int, bool]:
    """(parameter count, whether the lockstep training batches it: ``models.stackable``) of the architecture ``arch``
    for a system of sizes (n, m)."""
    key = (repr(arch), dimensions, width, depth)
    if key not in SHAPES:
        from nsl_hpc.models import build_model, stackable
        from nsl_hpc.models.blocks import parameter_count

        model = build_model(arch, *dimensions, width, depth)
        SHAPES[key] = parameter_count(model), stackable(model)
    return SHAPES[key]


class InputState(Study[InputStatePair]):
    name = "input_state"
    axes = ("system", "arch", "seed", "epochs", "data_tier", "width_tier", "depth_tier")
    length_axis = "epochs"
    shared_keys = ("system", "arch", "train", "data_per_trajectory", "draws", "metric")
    lockstep = True
    pair_schema = InputStatePair

    def check_size(self, label: str, key: str, value: Any, pair: InputStatePair) -> None:
        if key in TIER_OF:
            require_member(label, value, list(getattr(pair.tiers, TIER_OF[key])))
        milestones = pair.train.schedule_epochs
        if key == self.length_axis and milestones is not None:
            if pair.draws != "shared_across_epochs":
                raise ConfigError(f"train.schedule_epochs={milestones} (epoch milestones) needs tasks that differ "
                                  "only in epochs to be one model: add draws=shared_across_epochs (now draws="
                                  f"{pair.draws})")
            if value > milestones:
                raise ConfigError(f"{label}={value} is more than train.schedule_epochs={milestones}, the epochs of "
                                  "the milestone runs; raise it to the largest epoch count or set it to null")

    def check_pair(self, pair: InputStatePair) -> None:
        """The system builds and is finite on its initial box; the architecture builds for it and gives dx/dt and
        y of the right shapes on a sample batch, alone and stacked (``check_system``, ``check_architecture``)."""
        from nsl_hpc.studies.input_state.lockstep import check_architecture

        system = check_system(pair.system)
        check_architecture(pair.arch, system.state_dim, system.input_dim, math.ceil(min(pair.tiers.width) / 2),
                           math.ceil(min(pair.tiers.depth) / 2))

    def prepare_data(self, pair: InputStatePair) -> None:
        build_test_set(pair.system, ArrayCache(pair.cache_dir))

    def draw(self, task: Mapping[str, Any], pair: InputStatePair) -> dict[str, Any]:
        rng = self.draw_rng(task, pair.draws)
        data_size = rng.uniform(task["data_tier"] / 2, task["data_tier"])
        width, depth = draw_tier(rng, task["width_tier"]), draw_tier(rng, task["depth_tier"])
        n_traj = data_size / pair.data_per_trajectory
        points = training_points(n_traj, points_per_trajectory(pair.system))
        params, batched = model_shape(pair.arch, system_dimensions(pair.system), width, depth)
        return {"data_size": data_size, "n_traj": n_traj, "width": width, "depth": depth, "train_points": points,
                "params": params, "stackable": batched}

    def training_length(self, task: Mapping[str, Any], drawn: Mapping[str, Any],
                        pair: InputStatePair) -> dict[str, Any]:
        points, test_set = drawn["train_points"], pair.system.test_set
        repeat = pair.train.passes(drawn["n_traj"])
        return {"steps": task["epochs"] * batch_count(points * repeat, pair.train.batch_size),
                "flops": float(drawn["params"]) * task["epochs"] * points,
                # the same with the paper's "approximately 4 n_d n_h^2" parameters (docs/reproduction.md)
                "flops_paper": 4.0 * drawn["depth"] * drawn["width"] ** 2 * task["epochs"] * points,
                "test_points": test_set.trajectories * round(test_set.duration_s / pair.system.simulation.dt_s)}

    def train_and_score_group(self, tasks: Sequence[Task[InputStatePair]], on_progress: Callable[[], None],
                              checkpoint: Checkpointer | None = None) -> list[dict[str, Any]]:
        """Train the tasks' models in lockstep (they share system, arch and depth) and score each on the
        system's test set; with epoch milestones (train.schedule_epochs), tasks that differ only in epochs are
        one model, scored after each one's epochs. train_seconds is the training time (over every resume from
        ``checkpoint``) divided among the tasks; compiled: whether the step ran compiled (``compile``)."""
        import torch

        from nsl_hpc.studies.input_state.lockstep import (
            Snapshot,
            score_derivatives,
            score_mean_predictor,
            train_lockstep,
        )
        from nsl_hpc.studies.training import StepCompiler

        pair = tasks[0].pair
        runs: dict[tuple, list[int]] = {}
        for i, task in enumerate(tasks):
            runs.setdefault(model_of(task.keys, self.model_keys(pair.train.schedule_epochs, pair.draws)),
                            []).append(i)
        members = [self.member(tasks[run[0]], epochs=[tasks[i].coordinates["epochs"] for i in run])
                   for run in runs.values()]
        started = time.perf_counter()
        # auto is resolved by a sweep's planner; a user's modules (not stackable) run eagerly
        compiler = StepCompiler(tasks[0].compile == "always" and tasks[0].sizes.get("stackable", True))
        stack, snapshots = train_lockstep(members, pair.train, on_progress, checkpoint, compiler)
        train_seconds = (time.perf_counter() - started + trained_before(checkpoint)) / len(tasks)
        kept_at: dict[int, tuple[int, Snapshot]] = {}  # per task: its run's member index, its snapshot
        for k, (run, member_snapshots) in enumerate(zip(runs.values(), snapshots, strict=True)):
            by_epochs = {snapshot.epochs: snapshot for snapshot in member_snapshots}
            for i in run:
                kept_at[i] = (k, by_epochs[tasks[i].coordinates["epochs"]])
        kept = [kept_at[i] for i in range(len(tasks))]
        test_data = build_test_set(pair.system, ArrayCache(pair.cache_dir))
        scoring = scoring_progress(checkpoint, on_progress)  # a stop from now on keeps the trained models
        scoring()
        theta = torch.stack([snapshot.theta for _, snapshot in kept])
        dtype, normalization = getattr(torch, pair.train.dtype), pair.metric.normalization
        scores = score_derivatives(stack, test_data, [members[k].scaling for k, _ in kept], dtype, theta,
                                   [k for k, _ in kept], normalization, scoring)
        on_training_data = [score_derivatives(stack, members[k].data, [members[k].scaling], dtype,
                                              snapshot.theta[None], [k], normalization, scoring)[0]
                            for k, snapshot in kept]
        return [{**model_scores, "train_nmae": fitted["nmae"],
                 "mean_predictor_nmae": score_mean_predictor(test_data, members[k].data.dx.mean(axis=0),
                                                             normalization)["nmae"],
                 "steps": snapshot.outcome.steps,
                 "final_loss": snapshot.outcome.final_loss, "finite": snapshot.outcome.finite,
                 "train_seconds": train_seconds, "milestone": pair.train.schedule_epochs is not None,
                 "repeat": members[k].repeat,
                 "compiled": compiler.enabled}
                for model_scores, fitted, (k, snapshot) in zip(scores, on_training_data, kept, strict=True)]

    def member(self, task: Task[InputStatePair], epochs: Sequence[int]) -> "Member":
        """The task's initialised model and training data, ready for ``train_lockstep``, trained to the largest
        of ``epochs`` and kept after each."""
        import torch

        from nsl_hpc.models import build_model
        from nsl_hpc.studies.input_state.lockstep import Member
        from nsl_hpc.studies.input_state.scaling import Scaling

        pair, sizes = task.pair, task.sizes
        torch.manual_seed(self.seed_for("init", task.keys, pair.draws))
        model = build_model(pair.arch, *system_dimensions(pair.system), sizes["width"], sizes["depth"])
        data = build_training_set(pair.system, task.coordinates["seed"], sizes["n_traj"], ArrayCache(pair.cache_dir))
        return Member(model, data, Scaling.fit(data, pair.train.rescale_targets), max(epochs),
                      self.seed_for("shuffle", task.keys, pair.draws), milestones=tuple(epochs),
                      schedule_epochs=pair.train.schedule_epochs or 0, repeat=pair.train.passes(sizes["n_traj"]))
