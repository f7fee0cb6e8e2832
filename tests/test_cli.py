"""The command-line surface every ``python -m nsl_hpc.<verb>`` shares: --help per command, and misspelt keys."""

import importlib
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import nsl_hpc
from nsl_hpc.cli import usage
from nsl_hpc.config import compose_config
from nsl_hpc.core.errors import ConfigError
from tests.sweeps import TINY_GRID, nsl

# verb, its config, keys its help must name (its own ones, not every key of every config)
COMMANDS = [
    ("launch", "launch", ["dry_run=false", "launcher=<debug|local|slurm>", "lockstep.size=32", "epochs=64"]),
    ("train", "one_task", ["seed=0", "epochs=64", "system=<ball|", "force=false", "test_set=<1000x10s|100x100s|"]),
    ("status", "status", ["wait=false", "interval_s=10", "show_failures=10"]),
    ("predict", "predict", ["target=???", "metric=nmae", "resource=compute", "nsl.predict.decades=6"]),
    ("fit", "fit", ["metrics=null", "nsl.max_breaks=4", "nsl.envelope=step"]),
    ("report", "report", ["mlflow.tracking_uri=null", "nsl.bootstrap=200", "figures."]),
    ("resubmit", "resubmit", ["states=[failed, frozen, timeout, missing, corrupt]", "time_factor=1.0"]),
    ("merge", "merge", ["sweep_dir=???"]),
    ("clean", "clean", ["dry_run=false"]),
    ("place_data", "place_data", ["source=null", "download=true", "systems=[silverbox, wiener_hammerstein, "]),
]


@pytest.mark.parametrize(("verb", "config_name", "keys"), COMMANDS, ids=[c[0] for c in COMMANDS])
def test_help_says_what_the_command_does_with_two_examples_and_its_own_keys(verb, config_name, keys):
    text = usage(importlib.import_module(f"nsl_hpc.{verb}").__doc__, config_name)
    assert text.count(f"python -m nsl_hpc.{verb} ") >= 2, text  # two examples
    for key in keys:
        assert key in text, (key, text)
    assert "Current config" not in text and "_target_" not in text
    if verb in ("status", "predict", "fit"):
        assert "system=<" not in text and "launcher=<" not in text  # groups the command does not read


def test_launch_help_shows_the_chosen_launchers_settings_and_every_sweep(tmp_path, monkeypatch):
    """launch --help lists the keys of the launcher it would use (local by default, launcher=slurm's with it) with
    their types and one line each, and every sweep by name, the user's too."""
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "my_grid.yaml").write_text("# @package _global_\n# My own grid of the motor.\n")
    monkeypatch.setenv("NSL_HPC_CONFIG_DIR", str(tmp_path))
    doc = importlib.import_module("nsl_hpc.launch").__doc__
    local, slurm = usage(doc, "launch"), usage(doc, "launch", ["+sweep=demo", "launcher=slurm"])
    assert "launcher.workers=null                    (int | None) processes at once" in local
    assert "  launcher.partition=" not in local
    for key in ("partition=null", "account=null", "qos=null", "mem=2G", "max_running=null", "extra_sbatch={}",
                "setup=[]", "hold=False"):
        assert f"  launcher.{key}" in slurm, key
    for sweep in ("demo", "input_state", "input_output", "repro"):
        assert re.search(rf"^  {sweep} +\S", slurm, re.MULTILINE), sweep
    assert re.search(r"^  my_grid +My own grid of the motor\.", slurm, re.MULTILINE)


@pytest.mark.parametrize(("overrides", "config_name", "message"), [
    (["sweep_dir=x", "wiat=true"], "status", "unknown key 'wiat' (did you mean 'wait'?)"),
    (["train.lrr=0.01"], "one_task", "unknown key 'train.lrr' (did you mean 'train.lr'?)"),
    (["+train.lrr=0.01"], "one_task", "unknown key 'train.lrr' (did you mean 'train.lr'?); + only selects"),
    (["+swep=demo"], "launch", "unknown key 'swep' (did you mean 'sweep'?)"),
    (["systm=ball"], "one_task", "unknown key 'systm' (did you mean 'system'?)"),
    (["nothing.like.it=1"], "one_task", "unknown key 'nothing.like.it' (--help lists the keys)"),
])
def test_a_misspelt_key_names_the_closest_one_and_never_suggests_plus(overrides, config_name, message):
    with pytest.raises(ConfigError) as error:
        compose_config(overrides, config_name)
    assert str(error.value).startswith(message), str(error.value)
    assert "+wiat" not in str(error.value) and "To append" not in str(error.value)


def test_plus_still_selects_a_group_and_adds_sbatch_flags():
    cfg = compose_config(["+sweep=demo", "launcher=slurm", "+launcher.extra_sbatch.constraint=cpu"], "launch")
    assert cfg.sweep.name == "demo" and cfg.launcher.extra_sbatch.constraint == "cpu"


def test_every_command_a_message_or_doc_names_exists():
    """Each ``python -m nsl_hpc.<module>`` the code prints or documents is a command (it runs its main)."""
    package = Path(nsl_hpc.__file__).parent
    named = {match for path in package.rglob("*.py")
             for match in re.findall(r"python -m (nsl_hpc(?:\.\w+)+)", path.read_text())}
    assert "nsl_hpc.merge" in named
    for module in sorted(named):
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin, module
        if spec.submodule_search_locations:  # a package runs its __main__
            spec = importlib.util.find_spec(f"{module}.__main__")
            assert spec is not None and spec.origin, f"{module} has no __main__"
        assert 'if __name__ == "__main__":' in Path(spec.origin).read_text(), f"{module} is no command"


def test_the_commands_that_read_plan_or_fit_a_sweep_start_without_torch():
    """The commands import no torch (~1.5 s of their start) until a task trains (launch, resubmit) or a fit by
    nsl.objective=study runs."""
    verbs = ("status", "merge", "clean", "resubmit", "launch", "fit", "report", "predict")
    code = (f"import sys; import {', '.join(f'nsl_hpc.{verb}' for verb in verbs)}; "
            "print(sorted(name for name in sys.modules if name == 'torch' or name.startswith('torch.')))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


# A reader that goes away (| head -1) ends a command quietly, not with a BrokenPipeError traceback.
@pytest.mark.e2e
def test_a_closed_pipe_ends_status_quietly(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    read, write = os.pipe()
    os.close(read)
    result = subprocess.run([sys.executable, "-m", "nsl_hpc.status", f"sweep_dir={sweep_dir}"], stdout=write,
                            stderr=subprocess.PIPE, text=True)
    os.close(write)
    assert result.returncode == 1 and result.stderr == ""


@pytest.mark.e2e
def test_the_librarys_progress_lines_follow_the_log_level(tmp_path, monkeypatch):
    """What the sweep machinery reports (``finished: 1 ok``) goes through logging: a plain line at INFO (the
    default), none at $NSL_HPC_LOG_LEVEL=WARNING; an unknown level is one line, exit 2, before any work."""
    one_task = [*TINY_GRID, "sweep.grid.seed=[0]", "launcher=debug"]
    launched = nsl("launch", *one_task, f"sweep_dir={tmp_path / 'info'}")
    assert launched.returncode == 0 and "finished: 1 ok" in launched.stdout, launched.stderr
    monkeypatch.setenv("NSL_HPC_LOG_LEVEL", "warning")
    quiet = nsl("launch", *one_task, f"sweep_dir={tmp_path / 'quiet'}")
    assert quiet.returncode == 0 and "finished" not in quiet.stdout and "1 tasks" in quiet.stdout, quiet.stdout
    monkeypatch.setenv("NSL_HPC_LOG_LEVEL", "loud")
    refused = nsl("launch", *one_task, f"sweep_dir={tmp_path / 'refused'}")
    assert refused.returncode == 2 and not (tmp_path / "refused").exists()
    assert refused.stderr == ("error: $NSL_HPC_LOG_LEVEL='loud' is unknown; choose one of: DEBUG, INFO, WARNING, "
                              "ERROR\n")
