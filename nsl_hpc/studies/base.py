"""What a study is (``Study``): which coordinates a task has (its grid axes), how its sizes are drawn from them,
and how it trains and is scored; plus the checks of coordinate values every study uses."""

import dataclasses
import functools
import math
import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from nsl_hpc.config.arch import Arch
from nsl_hpc.config.identity import identity_values, with_stored_defaults
from nsl_hpc.config.mapping import plain
from nsl_hpc.config.schema import field_names, setting, typed
from nsl_hpc.config.targets import TARGET, package_target
from nsl_hpc.core.checkpoint import Checkpointer
from nsl_hpc.core.errors import require_positive_int
from nsl_hpc.core.seeding import stable_hash, stable_seed

DRAWS = ("per_task", "shared_across_epochs")


@dataclass(frozen=True)
class Tiers:
    """The tiers a grid may use; a task outside them is refused before any work."""

    width: list[int] = setting("n_h~ values", 1, nonempty=True)
    depth: list[int] = setting("n_d~ (input-state) or n_d (input-output) values", 1, nonempty=True)


@dataclass(frozen=True)
class Pair:
    """The settings every task of one (system, arch) shares, typed once where a command or a job reads the pair's
    config (``Study.pair``) and passed down as this instance to the study's checks, draws, data, models and
    training. ``values``: the plain config it was typed from (what task ids hash, configs/<system>__<arch>.yaml
    stores, a row records)."""

    arch: Arch = setting("the architecture")
    system: Any = setting("the system (each study types its own)")
    train: Any = setting("how each model trains (each study types its own)")
    tiers: Tiers = setting("the allowed tiers")
    draws: str = setting("per_task: a task's draws depend on all its coordinates; shared_across_epochs: on all but "
                         "its training length", choices=DRAWS)
    cache_dir: str = setting("simulated trajectories and records")
    values: dict[str, Any] = dataclasses.field(default_factory=dict, compare=False, repr=False, kw_only=True)


P = TypeVar("P", bound=Pair)


@dataclass(frozen=True)
class Task(Generic[P]):
    """A task as its study trains it: its pair's typed settings, its coordinates (the study's axes and sweep_seed),
    its id, its drawn sizes, and whether its training steps compile (``compile``: always or never; a sweep's
    planner resolves auto)."""

    pair: P
    coordinates: dict[str, Any]
    task_id: str
    sizes: dict[str, Any]
    compile: str

    @property
    def keys(self) -> dict[str, Any]:
        """Its coordinates and task_id (what seeds and ``model_of`` read)."""
        return {**self.coordinates, "task_id": self.task_id}


def draw_tier(rng: random.Random, tier: int) -> int:
    """An integer drawn uniformly in [ceil(tier / 2), tier]."""
    return rng.randint(math.ceil(tier / 2), tier)


class Study(Generic[P]):
    """What differs between studies. Subclasses set the class attributes and implement the methods; their methods
    take the typed settings of a (system, arch), ``pair_schema``."""

    name: str
    axes: tuple[str, ...]  # grid axes in expansion order: "system", "arch", "seed", then the size coordinates
    length_axis: str  # the axis of training length (with shared draws, longer runs of the same model)
    shared_keys: tuple[str, ...]  # config groups and keys that change the outcome of every task of a pair
    lockstep: bool = False  # train_and_score_group trains same-shape tasks together (in lockstep)
    pair_schema: type[P]  # the typed settings of a (system, arch): system, arch, train, ...

    @property
    def size_axes(self) -> tuple[str, ...]:
        """The coordinates sizes are drawn from and training length is set by (checked by check_coordinate)."""
        return tuple(axis for axis in self.axes if axis not in ("system", "arch", "seed"))

    @property
    def task_keys(self) -> tuple[str, ...]:
        """Scalar coordinates that differ between the tasks of one (system, arch), for the task id."""
        return ("sweep_seed", *(axis for axis in self.axes if axis not in ("system", "arch")))

    @functools.cache  # noqa: B019 (studies are a few long-lived objects)
    def draw_keys(self, draws: str) -> tuple[str, ...]:
        """What the random draws of a task (sizes, initial weights, batch order) depend on: every coordinate
        (``draws: per_task``, Algorithms 1 and 2) or all but the training length (``shared_across_epochs``)."""
        return ("sweep_seed", *(axis for axis in self.axes if draws == "per_task" or axis != self.length_axis))

    def pair(self, values: Mapping[str, Any]) -> P:
        """The typed settings of a (system, arch) from its plain or composed config ``values`` (one-line
        ConfigError naming a bad key), ``values`` kept plain beside them."""
        given = {name: values[name] for name in field_names(self.pair_schema) if name != "values" and name in values}
        return dataclasses.replace(typed(self.pair_schema, given, ""), values=plain(values))

    def model_keys(self, schedule_epochs: int | None, draws: str) -> tuple[str, ...]:
        """The coordinates that make tasks one model (``model_of``): with epoch milestones (a lockstep study
        with ``train.schedule_epochs``, which needs shared draws) the draw keys, so tasks that differ only in
        training length are one run kept after each one's length; else none (a model per task)."""
        if not self.lockstep or schedule_epochs is None:
            return ()
        return self.draw_keys(draws)

    def draw_rng(self, task: Mapping[str, Any], draws: str) -> random.Random:
        """The generator of a task's size draws (Python's Mersenne Twister: seeding it costs a third of numpy's,
        which matters for the 63,504 draws of a manifest)."""
        return random.Random(stable_seed("sizes", *(task[key] for key in self.draw_keys(draws))))

    def seed_for(self, purpose: str, task: Mapping[str, Any], draws: str) -> int:
        """The seed of one random stream of a task ("init", "shuffle")."""
        return stable_seed(purpose, *(task[key] for key in self.draw_keys(draws)))

    def shared_identity(self, values: Mapping[str, Any]) -> str:
        """Hash of what a pair's plain config ``values`` gives each of its tasks' ids (``config.identity``: its
        ``shared_keys`` groups less the one list of excluded settings), with a rehearsal's settings in a
        rehearsal."""
        shared = identity_values(self.name, self.shared_keys, values)
        if values.get("rehearsal"):  # a rehearsal's synthetic outcomes: never a real sweep's tasks
            shared["rehearsal"] = values["rehearse"]
        return stable_hash(shared)

    def with_stored_defaults(self, cfg: dict[str, Any]) -> dict[str, Any]:
        """``cfg``, a pair's stored config, with the excluded settings it lacks (stored before they existed) at the
        value every task had then (``config.identity.with_stored_defaults``), and a system or arch stored before
        targets with the package's ``_target_`` of its name (``package_target``)."""
        cfg = with_stored_defaults(self.name, cfg)
        for group in ("system", "arch"):
            target = package_target(group, cfg[group]["name"])
            if TARGET not in cfg[group] and target is not None:
                cfg[group][TARGET] = target
        return cfg

    def check_coordinate(self, label: str, key: str, value: Any, pair: P) -> None:
        """Raise ConfigError when ``value`` is not allowed for coordinate ``key`` (``label`` names it), or, for
        the training length, when the settings that go with it are not."""
        require_positive_int(label, value)
        self.check_size(label, key, value, pair)

    def check_size(self, label: str, key: str, value: Any, pair: P) -> None:
        """The study's own checks of a coordinate (``check_coordinate``)."""

    def check_pair(self, pair: P) -> None:
        """Raise ConfigError when a (system, arch) cannot run at all (e.g. its data is missing)."""

    def check_task(self, task: Mapping[str, Any], sizes: Mapping[str, Any], pair: P) -> None:
        """Raise ConfigError when a task's drawn sizes cannot run (checked before any work)."""

    def prepare_data(self, pair: P) -> None:
        """Simulate (or read) into ``cache_dir`` the data every task of a (system, arch) shares, so a sweep's
        first jobs do not all simulate it at once (launch calls it before dispatching)."""

    def sizes(self, task: Mapping[str, Any], pair: P) -> dict[str, Any]:
        """The sizes a task draws and what follows: at least train_points, params, steps and flops."""
        drawn = self.draw(task, pair)
        return {**drawn, **self.training_length(task, drawn, pair)}

    def sizes_in(self, row: Mapping[str, Any]) -> dict[str, Any]:
        """The drawn sizes of a manifest row: its columns other than task_id and the coordinates."""
        coordinates = {"task_id", "system", "arch", *self.task_keys}
        return {key: value for key, value in row.items() if key not in coordinates}

    def draw(self, task: Mapping[str, Any], pair: P) -> dict[str, Any]:
        """The sizes drawn from the task's coordinates (its training length aside): train_points, params..."""
        raise NotImplementedError

    def training_length(self, task: Mapping[str, Any], drawn: Mapping[str, Any], pair: P) -> dict[str, Any]:
        """steps (optimizer steps) and flops (the compute resource) of a task with sizes ``drawn``."""
        raise NotImplementedError

    def train_and_score_group(self, tasks: Sequence[Task[P]], on_progress: Callable[[], None],
                              checkpoint: Checkpointer | None = None) -> list[dict[str, Any]]:
        """Train each task's model and score it: nmae, nmse, steps, final_loss, finite, train_seconds and study
        extras; the tasks (of one pair and depth) train together in lockstep, continuing from ``checkpoint`` and
        writing it as training goes on."""
        raise NotImplementedError


def model_of(task: Mapping[str, Any], model_keys: Sequence[str]) -> tuple:
    """Which model a task (a manifest row, or coordinates with its task_id) trains: tasks with equal values
    are one model. ``model_keys``: ``Study.model_keys``; none means one model per task."""
    return tuple(task[key] for key in model_keys) if model_keys else (task["task_id"],)

