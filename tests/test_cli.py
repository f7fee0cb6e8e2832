"""The command-line surface every ``python -m nsl_hpc.<verb>`` shares: --help per command, and misspelt keys."""

import importlib
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml

import nsl_hpc
from nsl_hpc.cli import usage
from nsl_hpc.config import compose_config
from nsl_hpc.errors import ConfigError
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
    ("place_data", "place_data", ["source=???", "systems=[silverbox, wiener_hammerstein, "]),
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


@pytest.mark.e2e
def test_a_users_own_sweep_and_site_settings_run_from_outside_an_installed_package(tmp_path):
    """nsl_hpc installed as a wheel (not this checkout), run from elsewhere: `--config-dir` (or
    $NSL_HPC_CONFIG_DIR) adds the user's sweep/<name>.yaml and local/default.yaml to the package's configs."""
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "--no-deps",
                    "--no-build-isolation", "--target", str(site), str(Path(nsl_hpc.__file__).parents[1])],
                   check=True, capture_output=True, timeout=300)
    mine = tmp_path / "my conf"
    (mine / "sweep").mkdir(parents=True)
    (mine / "local").mkdir()
    (mine / "sweep" / "my_grid.yaml").write_text(  # the package's demo grid, narrowed
        "# @package _global_\ndefaults:\n  - demo\nsweep:\n  name: my_grid\n  grid:\n    system: [spring]\n"
        "    arch: [input_affine]\n")
    (mine / "local" / "default.yaml").write_text("# @package _global_\nsweep_seed: 7\n")  # site settings, last
    env = {**os.environ, "PYTHONPATH": str(site)}

    def run(*args: str, **extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=tmp_path,
                              env={**env, **extra}, timeout=300)

    assert run("-c", "import nsl_hpc; print(nsl_hpc.__file__)").stdout.startswith(str(site))
    launched = run("-m", "nsl_hpc.launch", "--config-dir", str(mine), "+sweep=my_grid", "launcher=debug",
                   "dry_run=true", "sweep_dir=mine")
    assert launched.returncode == 0, launched.stderr
    launch = yaml.safe_load((tmp_path / "mine" / "launch.yaml").read_text())
    assert (launch["sweep"]["name"], launch["sweep_seed"]) == ("my_grid", 7)
    assert pq.read_metadata(tmp_path / "mine" / "manifest.parquet").num_rows == 36  # 2 seeds x 3 x 3 x 2
    by_variable = run("-m", "nsl_hpc.launch", "+sweep=my_grid", "launcher=debug", "dry_run=true", "sweep_dir=env",
                      NSL_HPC_CONFIG_DIR=str(mine))
    assert by_variable.returncode == 0, by_variable.stderr
    assert "name: my_grid" in run("-m", "nsl_hpc.launch", f"--config-dir={mine}", "+sweep=my_grid", "--cfg").stdout
    without = run("-m", "nsl_hpc.launch", "+sweep=my_grid", "launcher=debug", "dry_run=true")
    assert without.returncode == 2 and "unknown sweep 'my_grid'" in without.stderr
    missing = run("-m", "nsl_hpc.status", "--config-dir", str(tmp_path / "nowhere"), "sweep_dir=mine")
    assert missing.returncode == 2 and len(missing.stderr.splitlines()) == 1 and "is no directory" in missing.stderr


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
    """What the sweep machinery reports (``finished: 4 ok``) goes through logging: a plain line at INFO (the
    default), none at $NSL_HPC_LOG_LEVEL=WARNING; an unknown level is one line, exit 2, before any work."""
    launched = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={tmp_path / 'info'}")
    assert launched.returncode == 0 and "finished: 4 ok" in launched.stdout, launched.stderr
    monkeypatch.setenv("NSL_HPC_LOG_LEVEL", "warning")
    quiet = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={tmp_path / 'quiet'}")
    assert quiet.returncode == 0 and "finished" not in quiet.stdout and "4 tasks" in quiet.stdout, quiet.stdout
    monkeypatch.setenv("NSL_HPC_LOG_LEVEL", "loud")
    refused = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={tmp_path / 'refused'}")
    assert refused.returncode == 2 and not (tmp_path / "refused").exists()
    assert refused.stderr == ("error: $NSL_HPC_LOG_LEVEL='loud' is unknown; choose one of: DEBUG, INFO, WARNING, "
                              "ERROR\n")
