"""One list of what stays out of a task's identity (nsl_hpc/config/identity.py): every setting of the shipped configs
is either in a task's id (it moves the id) or on that list (it does not), and a setting left out only at the value
every task had before it existed keeps the ids of a config stored before then."""

import copy
from collections.abc import Iterator
from typing import Any

import pytest
from omegaconf import OmegaConf

from nsl_hpc.config import compose_config, config_dir
from nsl_hpc.config.identity import ANY, EXCLUDED, NOT_STORED, OUT_OF_IDENTITY, with_stored_defaults
from nsl_hpc.config.mapping import plain
from nsl_hpc.registry import OUTCOME, groups
from nsl_hpc.studies import Study, study_named
from nsl_hpc.sweep.task import task_id_from


def options(group: str, study: str) -> list[str]:
    """The shipped options of a config group that belong to ``study``."""
    names = sorted(path.stem for path in (config_dir() / group).glob("*.yaml"))
    return [name for name in names if OmegaConf.load(config_dir() / group / f"{name}.yaml").study == study]


PAIRS = [(study, system, arch) for study in ("input_state", "input_output")
         for system in options("system", study) for arch in options("arch", study)]


DEMO = {"input_state": "demo", "input_output": "io_demo"}  # a sweep of each study, for launch's config


def composed(study: str, system: str, arch: str, config_name: str = "config") -> dict[str, Any]:
    """The plain config of a task (``config``: train's) or of a launch (``launch``, with the study's demo sweep)."""
    sweep = [f"+sweep={DEMO[study]}"] if config_name == "launch" else []
    return plain(compose_config([f"study={study}", f"system={system}", f"arch={arch}", *sweep], config_name))


def identity_keys(study: Study) -> set[str]:
    """The top-level keys of a config in a task's id: its pair's outcome groups, its coordinates, a rehearsal's."""
    return {*study.shared_keys, *study.task_keys, "system", "arch", "rehearsal", "rehearse"}


def id_of(study: Study, values: dict[str, Any]) -> str:
    return task_id_from(study, study.shared_identity(values), values)


def leaves(value: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """The paths of a plain config's leaves (a list is one leaf)."""
    if isinstance(value, dict) and value:
        for key, item in value.items():
            yield from leaves(item, (*path, key))
    else:
        yield path


def perturbed(values: dict[str, Any], path: tuple[str, ...]) -> dict[str, Any]:
    """``values`` with the leaf at ``path`` changed (a bool negated, anything else a string no setting has)."""
    changed = copy.deepcopy(values)
    parent = changed
    for key in path[:-1]:
        parent = parent[key]
    leaf = parent[path[-1]]
    parent[path[-1]] = (not leaf) if isinstance(leaf, bool) else "<perturbed>"
    return changed


def left_out_at_every_value(study: str, arch: str, path: tuple[str, ...]) -> bool:
    """Whether the list leaves the leaf at ``path`` out of the id whatever its value: the whole top-level key, an
    excluded setting at ANY value, or another architecture's entry of a per-architecture setting."""
    if path[0] in OUT_OF_IDENTITY:
        return True
    for entry in EXCLUDED:
        if not entry.applies(study, arch):
            continue
        if entry.group == "*" and entry.key in path[1:] and entry.at == ANY:
            return True
        if path[:2] == (entry.group, entry.key) and (
                entry.at == ANY or (entry.per_architecture and len(path) > 2 and path[2] != arch)):
            return True
    return False


@pytest.mark.parametrize("config_name", ["config", "launch"])
def test_every_top_level_key_is_in_the_identity_or_on_the_list(config_name):
    seen: set[str] = set()
    for study_name, system, arch in PAIRS:
        values = composed(study_name, system, arch, config_name)
        inside = identity_keys(study_named(study_name))
        for key in values:
            assert (key in inside) != (key in OUT_OF_IDENTITY), f"{study_name}: {key}"
        seen.update(values)
    if config_name == "launch":
        assert set(OUT_OF_IDENTITY) <= seen  # the list names no key that is gone
    outcome_groups = {group.name for group in groups() if group.kind == OUTCOME}
    assert not outcome_groups & set(OUT_OF_IDENTITY)


@pytest.mark.parametrize("pair", PAIRS, ids=["/".join(pair) for pair in PAIRS])
def test_every_setting_moves_the_task_id_unless_the_list_leaves_it_out(pair):
    study_name, system, arch = pair
    study = study_named(study_name)
    values = {**composed(study_name, system, arch, "launch"), "rehearsal": True}
    before = id_of(study, values)
    moved, kept = [], []
    for path in leaves(values):
        stays = id_of(study, perturbed(values, path)) == before
        assert stays == left_out_at_every_value(study_name, arch, path), ".".join(path)
        (kept if stays else moved).append(path)
    assert len(moved) > 20 and kept  # both sides of the list are exercised


@pytest.mark.parametrize("entry", [entry for entry in EXCLUDED if entry.stored != NOT_STORED],
                         ids=lambda entry: entry.setting)
def test_a_config_stored_before_an_excluded_setting_keeps_its_ids(entry):
    """A pair's config stored before the setting existed (it lacks the key) reads it at ``stored`` and has the ids of
    a config that sets it so."""
    study_name, system, arch = next(pair for pair in PAIRS if entry.applies(pair[0], pair[2]))
    study = study_named(study_name)
    values = composed(study_name, system, arch)
    values[entry.group][entry.key] = entry.stored
    stored_before = copy.deepcopy(values)
    del stored_before[entry.group][entry.key]
    assert id_of(study, stored_before) == id_of(study, values)
    read = plain(with_stored_defaults(study_name, OmegaConf.create(stored_before)))
    assert read[entry.group][entry.key] == entry.stored and id_of(study, read) == id_of(study, values)


def test_a_users_target_is_in_the_identity_and_the_packages_is_not():
    study = study_named("input_state")
    values = composed("input_state", "spring", "unstructured")
    own = copy.deepcopy(values)
    own["arch"]["_target_"] = "my_models.Net"
    package = copy.deepcopy(values)
    package["arch"]["_target_"] = "nsl_hpc.models.unstructured.Other"
    assert id_of(study, package) == id_of(study, values) != id_of(study, own)
