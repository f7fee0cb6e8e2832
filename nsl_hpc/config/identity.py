"""What stays out of a task's identity, in one list (as Dora's ``exclude``). A task's id is the hash of its scalar
coordinates (``Study.task_keys``) and of its pair's outcome settings: the top-level keys ``Study.shared_keys``
names (system, arch, train and the study's own) and, in a rehearsal, ``rehearse``. Everything else stays out:

- ``OUT_OF_IDENTITY``: every other top-level key of the configs that make tasks (train's and launch's), with why;
- ``EXCLUDED``: settings inside the outcome groups, at any value or only at the value every task had before the
  setting existed (``at``: a sweep made then keeps its ids; another value is another task).

``identity_values`` applies ``EXCLUDED`` to a pair's plain config, ``outcome_values`` its entries for every group
(``*.key``); ``with_stored_defaults`` reads a pair's config stored before a setting existed at the value every task
had then. tests/test_identity.py holds every setting of the shipped configs to one side or the other.
"""

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.arch import IO_ARCHITECTURES
from nsl_hpc.config.targets import PACKAGE_PREFIX

ANY = "<any value>"  # ``Excluded.at``: out of the identity at every value
IN_PACKAGE = "<a target inside the package>"  # ``Excluded.at``: a ``_target_`` the package's version identifies
NOT_STORED = "<not filled in>"  # ``Excluded.stored``: a config stored before the setting is left as it is

ROUNDING = "how a step is computed: float rounding only"
WHERE = "where files are, not what they hold"
RUN = "how jobs run (run.yaml; a resubmit may change it)"
WHICH = "which tasks a sweep runs and in what order or rounds"

OUT_OF_IDENTITY: dict[str, str] = {
    "study": "named by its system and arch (their own study key is in the identity)",
    "tiers": "the values a grid may use (a task's own tiers are its coordinates)",
    "out_dir": WHERE, "sweep_dir": WHERE, "cache_dir": WHERE, "compile_cache_dir": WHERE, "data_dir": WHERE,
    "task_id": "the id itself (train runs one task by it)",
    "force": "whether train replaces a row",
    "threads": ROUNDING, "compile": ROUNDING,
    "launcher": RUN, "lockstep": RUN, "packing": RUN, "cost": RUN, "checkpoint": RUN, "watchdog": RUN,
    "sweep": WHICH, "budget": WHICH, "max_tasks": WHICH, "dry_run": WHICH,
    "allow_shared_sweep_dir": "what a launch may do", "allow_code_change": "what a launch may do",
    "nsl": "post-processing of the rows",
    "fault": "test-only faults",
}


@dataclass(frozen=True)
class Excluded:
    """``setting`` ("group.key"; "*.key": that key in every outcome group, at any depth) out of a task's identity
    ``at`` every value (ANY), only at one value (every task's before the setting existed), or (IN_PACKAGE) where it
    names a target inside the package. ``study`` / ``arch``: the only study or architecture it applies to.
    ``per_architecture``: the setting holds a value per architecture, of which the pair's own stands for it.
    ``stored``: the value a pair's config stored before the setting existed is read with."""

    setting: str
    why: str
    at: Any = ANY
    stored: Any = NOT_STORED
    study: str | None = None
    arch: str | None = None
    per_architecture: bool = False

    @property
    def group(self) -> str:
        return self.setting.split(".", 1)[0]

    @property
    def key(self) -> str:
        return self.setting.split(".", 1)[1]

    def applies(self, study: str, arch: str) -> bool:
        return self.study in (None, study) and self.arch in (None, arch)

    def leaves_out(self, value: Any) -> bool:
        """Whether this setting at ``value`` stays out of the identity."""
        if self.at == IN_PACKAGE:
            return str(value).startswith(PACKAGE_PREFIX)
        return self.at == ANY or value == self.at


EXCLUDED: tuple[Excluded, ...] = (
    Excluded("*.data_dir", WHERE),
    Excluded("*._target_", "the package's own builder: its version identifies the code, as the group's name did "
             "before targets (a user's target stays in)", at=IN_PACKAGE),
    Excluded("train.repeat", "each epoch's data once, as before the setting", at=1, stored=1, study="input_state"),
    Excluded("train.weight_decay", "no weight decay, as before the setting", at=0.0, stored=0.0,
             study="input_state"),
    Excluded("train.repeat_by_trajectories", "no repeat by trajectory count, as before the setting", at=None,
             stored=None, study="input_state"),
    Excluded("train.schedule", "warmup_cosine, every task's schedule before the setting; another architecture's "
             "schedule is not the pair's", at="warmup_cosine", stored=dict.fromkeys(IO_ARCHITECTURES, "warmup_cosine"),
             study="input_output", per_architecture=True),
    Excluded("train.rollout_segment", ROUNDING + " (how a compiled SUBNET step recomputes its rollout)",
             stored={"feature_major": 10, "batch_major": 10}, study="input_output"),
    Excluded("arch.bypass", "no linear path, every NARX task's layout before the setting", at=False, stored=False,
             study="input_output", arch="narx"),
    Excluded("arch.zero_bias", "PyTorch's biases, every NARX task's before the setting", at=False, stored=False,
             study="input_output", arch="narx"),
)
EVERY_GROUP = {entry.key: entry for entry in EXCLUDED if entry.group == "*"}


def outcome_values(value: Any) -> Any:
    """``value`` (a group's plain values) without what ``EXCLUDED`` leaves out in every group (``*.key``): where data
    lies, the package's own targets."""
    if isinstance(value, Mapping):
        return {key: outcome_values(item) for key, item in value.items()
                if not (key in EVERY_GROUP and EVERY_GROUP[key].leaves_out(item))}
    return value


def identity_values(study: str, shared_keys: Sequence[str], values: Mapping[str, Any]) -> dict[str, Any]:
    """What of a pair's plain config ``values`` its tasks' ids hash: the ``shared_keys`` groups, less ``EXCLUDED``."""
    shared = {key: outcome_values(values[key]) for key in shared_keys}
    arch = values["arch"]["name"]
    for entry in EXCLUDED:
        group = shared.get(entry.group)
        if not entry.applies(study, arch) or not isinstance(group, dict) or entry.key not in group:
            continue
        if entry.per_architecture:
            group[entry.key] = dict(group[entry.key]).get(arch, entry.at)
        if entry.leaves_out(group[entry.key]):
            del group[entry.key]
    return shared


def with_stored_defaults(study: str, cfg: dict[str, Any]) -> dict[str, Any]:
    """``cfg``, a pair's stored config, with the excluded settings it lacks (it was stored before they existed) at
    the value every task had then."""
    for entry in EXCLUDED:
        if entry.stored != NOT_STORED and entry.applies(study, cfg["arch"]["name"]) \
                and entry.key not in cfg[entry.group]:
            cfg[entry.group][entry.key] = copy.deepcopy(entry.stored)
    return cfg
