"""Typed config groups (nsl_hpc/config/schema.py): each group's owner refuses a bad value in one line naming the
key, and --help reads the fields' own documentation."""

import dataclasses
import typing

import pytest
from omegaconf import OmegaConf

from nsl_hpc.cli import schema_docs
from nsl_hpc.config import compose_config, config_dir
from nsl_hpc.config.arch import STUDIES, arch_settings
from nsl_hpc.config.schema import field_names, typed
from nsl_hpc.config.system import InputOutputSystem, InputStateSystem
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import studies
from nsl_hpc.studies.settings import InputOutputTrain, InputStateTrain, RolloutSegment
from nsl_hpc.sweep.run_settings import RUN_GROUPS, Checkpoint, Cost, Watchdog, run_settings
from nsl_hpc.sweep.task import check_settings
from tests.sweeps import nsl


@pytest.fixture(scope="module")
def launch():
    return compose_config(["+sweep=demo"], "launch")


def test_the_launch_configs_groups_are_typed(launch):
    settings = run_settings(launch)
    assert settings.lockstep.size == launch.lockstep.size and isinstance(settings.watchdog, Watchdog)
    assert settings.cost.compile_s["narx"] == launch.cost.compile_s.narx
    io = typed(InputOutputTrain, compose_config(["study=input_output"], "one_task").train, "train")
    assert io.rollout_segment == RolloutSegment(10, 10)
    assert typed(InputStateTrain, launch.train, "train").schedule == launch.train.schedule


@pytest.mark.parametrize(("change", "message"), [
    ({"overrun_factor": float("inf")}, "watchdog.overrun_factor=inf must be a finite number in [1, 1000]"),
    ({"overrun_factor": True}, "watchdog.overrun_factor=True must be a finite number"),
    ({"heartbeat_timeout_s": "900"}, "watchdog.heartbeat_timeout_s='900' must be a finite number in (0, 86400]"),
    ({"worker_silence_s": 10}, "watchdog.worker_silence_s=10 must be a finite number in [30, 86400]"),
    ({"beat": 1}, "watchdog.beat is unknown; watchdog has: heartbeat_timeout_s, overrun_factor, worker_silence_s"),
])
def test_a_group_refuses_a_bad_value_naming_its_key(launch, change, message):
    values = {**OmegaConf.to_container(launch.watchdog), **change}
    with pytest.raises(ConfigError) as error:
        typed(Watchdog, values, "watchdog")
    assert str(error.value).startswith(message)


def test_missing_keys_nested_groups_and_rules_between_fields(launch):
    with pytest.raises(ConfigError, match=r"^checkpoint.every_minutes is missing \(written every"):
        typed(Checkpoint, {}, "checkpoint")
    assert typed(Checkpoint, {"every_minutes": 0}, "checkpoint").every_minutes == 0  # also: 0, no checkpoints
    segments = {"feature_major": 10, "batch_major": 1.5}
    with pytest.raises(ConfigError, match=r"^train.rollout_segment.batch_major=1.5 must be a non-negative integer"):
        typed(RolloutSegment, segments, "train.rollout_segment")
    cost = {**OmegaConf.to_container(launch.cost), "compile_s": {}}
    with pytest.raises(ConfigError, match=r"^cost.compile_speedup.\w+ needs cost.compile_s"):
        typed(Cost, cost, "cost")
    train = {**OmegaConf.to_container(launch.train), "dtype": "float16"}
    with pytest.raises(ConfigError, match=r"^train.dtype='float16' is unknown; choose one of: float32, float64"):
        typed(InputStateTrain, train, "train")


@pytest.mark.e2e
def test_help_gives_each_typed_key_its_fields_documentation():
    docs = schema_docs()
    assert set(RUN_GROUPS) <= set(docs) and "train.rollout_segment.batch_major" in docs
    shown = nsl("launch", "--help").stdout
    for key in ("watchdog.overrun_factor", "lockstep.size", "cost.compile_s"):
        assert docs[key] in shown.replace("\n", " "), key


def test_system_and_arch_groups_are_checked_by_their_kind():
    sim = OmegaConf.to_container(compose_config(["study=input_output", "system=silverbox_sim"], "one_task").system)
    assert typed(InputOutputSystem, sim, "system").subnet.horizon == 150
    with pytest.raises(ConfigError, match=r"^system.score_on='arrow'; choose one of: test"):
        typed(InputOutputSystem, {**sim, "score_on": "arrow"}, "system")
    with pytest.raises(ConfigError, match=r"^system.fs_hz is missing: a simulated system \(duffing\)"):
        typed(InputOutputSystem, {key: value for key, value in sim.items() if key != "fs_hz"}, "system")
    ball = OmegaConf.to_container(compose_config(["system=ball"], "one_task").system)
    with pytest.raises(ConfigError, match=r"^system.initial_box\[0\]=\[2.0, -0.5\] must be \[low, high\]"):
        typed(InputStateSystem, {**ball, "initial_box": [[2.0, -0.5], *ball["initial_box"][1:]]}, "system")
    assert arch_settings({"name": "narx", "_target_": "nsl_hpc.models.narx.NARX", "study": "input_output",
                          "block": "tanh", "bypass": True, "zero_bias": True, "past_outputs": 50,
                          "past_inputs": 50}).past_inputs == 50
    with pytest.raises(ConfigError, match=r"^arch.hamiltonian='square' is unknown; choose one of: abs, plain"):
        arch_settings({"name": "port_hamiltonian", "_target_": "nsl_hpc.models.port_hamiltonian.PortHamiltonian",
                       "study": "input_state", "block": "tanh", "hamiltonian": "square", "dissipation": "square"})
    with pytest.raises(ConfigError, match=r"^arch._target_ is missing"):
        arch_settings({"name": "mlp", "study": "input_state", "block": "tanh"})


def test_a_tasks_fault_and_rehearsal_groups_are_checked_before_any_work():
    task = OmegaConf.to_container(compose_config(["system=ball"], "one_task"), resolve=True)
    check_settings(task)
    for group, change, message in [
        ("fault", {"kind": "crash"}, r"^fault.kind='crash' is unknown; choose one of: raise, hang, slow"),
        ("fault", {"heartbeat_s": -1}, r"^fault.heartbeat_s=-1 must be a finite number in \[0, 86400\]"),
        ("rehearse", {"frozen_share": 0.7, "failed_share": 0.5}, r"^rehearse.frozen_share \+ rehearse.failed_share"),
        ("rehearse", {"laws": {"nmae": task["rehearse"]["laws"]["nmae"]}}, r"^rehearse.laws has nmae: it needs"),
        ("rehearse", {"laws": {**task["rehearse"]["laws"], "nmse": {**task["rehearse"]["laws"]["nmse"], "beta": 0}}},
         r"^rehearse.laws.nmse.beta=0 must be a finite number in \(0, inf\)"),
    ]:
        with pytest.raises(ConfigError, match=message):
            check_settings({**task, group: {**task[group], **change}})


@pytest.mark.e2e
def test_a_launch_refuses_a_bad_rehearsal_setting_in_one_line(tmp_path):
    bad = nsl("launch", "+sweep=demo", "rehearsal=true", "rehearse.killed_jobs=-1", "dry_run=true",
              f"sweep_dir={tmp_path / 'sweep'}")
    assert bad.returncode == 2 and bad.stderr.startswith("error: rehearse.killed_jobs=-1 must be a non-negative")
    assert not (tmp_path / "sweep").exists()


def test_the_study_names_agree_wherever_they_are_named():
    """config.arch.STUDIES (what a system or arch may belong to), the studies the code runs and conf/study/."""
    assert set(STUDIES) == set(studies()) == {path.stem for path in (config_dir() / "study").glob("*.yaml")}
    for name in STUDIES:
        assert compose_config([f"study={name}"] + (["system=silverbox", "arch=narx"] if name == "input_output"
                                                   else []), "one_task").study.name == name


def test_the_registry_of_config_groups_agrees_with_what_the_code_does_with_them():
    """One registry (nsl_hpc.registry): its RUN groups are run.yaml's (what a resubmit may change), the groups of
    every study's task ids are OUTCOME groups, and each owner documents its keys for --help."""
    from nsl_hpc.registry import OUTCOME, RUN, groups
    from nsl_hpc.studies import studies
    from nsl_hpc.sweep.run_settings import RUN_KEYS

    kinds = {group.name: group.kind for group in groups()}
    assert [name for name, kind in kinds.items() if kind == RUN and name] == [key for key in RUN_KEYS
                                                                                if key != "compile"]
    assert "compile" in [key for group in groups() if not group.name for key in field_names(group.owners[0])]
    for study in studies().values():
        assert all(kinds[group] == OUTCOME for group in study.shared_keys if group in kinds), study.name
        owners = {group.name: group.owners for group in groups()}
        for name, owner in typing.get_type_hints(study.pair_schema).items():  # a pair's typed groups: registered
            if dataclasses.is_dataclass(owner):
                assert owner in owners[name], (study.name, name)
