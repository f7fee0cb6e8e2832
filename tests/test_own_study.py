"""A researcher's own study without a fork: examples/own_study (their system, model and measured records, named
by `_target_` and `source.kind: files` in their config dir) runs from a copy outside the checkout on nsl_hpc
installed as a wheel, and each broken system, model or record is one line, exit 2, before anything is written."""

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
import yaml

import nsl_hpc
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models import build_model, stackable
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_state.data import build_test_set, build_training_set
from nsl_hpc.studies.input_state.lockstep import Member, predict_derivatives, train_lockstep
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.sweep.rows import read_row

EXAMPLE = Path(nsl_hpc.__file__).parents[1] / "examples" / "own_study"
SMALL_STUDY = ["sweep.grid.seed=[0]", "sweep.grid.epochs=[16,64]", "sweep.grid.data_tier=[8]",
               "sweep.grid.width_tier=[16]"]  # 6 tasks: 3 archs
LIGHT_FITS = ["nsl.bootstrap=20", "nsl.max_breaks=1", "nsl.joint.bootstrap=10"]  # the fits themselves: test_nsl.py


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """nsl_hpc installed as a wheel into a folder of its own (not this checkout)."""
    folder = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "--no-deps",
                    "--no-build-isolation", "--target", str(folder), str(EXAMPLE.parents[1])],
                   check=True, capture_output=True, timeout=300)
    return folder


@pytest.fixture
def study(tmp_path) -> Path:
    """A copy of examples/own_study outside the checkout."""
    return Path(shutil.copytree(EXAMPLE, tmp_path / "own_study", ignore=shutil.ignore_patterns("__pycache__")))


def run(study: Path, site: Path, verb: str, *args: str) -> subprocess.CompletedProcess:
    """``python -m nsl_hpc.<verb> --config-dir conf args`` in ``study`` with PYTHONPATH=.:<site>, as the docs say."""
    env = {**os.environ, "PYTHONPATH": f".{os.pathsep}{site}"}
    return subprocess.run([sys.executable, "-m", f"nsl_hpc.{verb}", "--config-dir", "conf", *args],
                          capture_output=True, text=True, cwd=study, env=env, timeout=600)


@pytest.mark.e2e
@pytest.mark.slow
def test_a_users_own_sweep_and_site_settings_run_from_outside_an_installed_package(site, tmp_path):
    """nsl_hpc installed as a wheel (not this checkout), run from elsewhere: `--config-dir` (or
    $NSL_HPC_CONFIG_DIR) adds the user's sweep/<name>.yaml and local/default.yaml to the package's configs."""
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



@pytest.mark.e2e
@pytest.mark.slow
def test_your_own_system_and_model_train_fit_and_report_from_a_wheel(study, site):
    """The example's system and models, launched, reported and predicted by the installed wheel from the study's own
    folder (its records: tests/cluster/test_own_study_slurm.py runs own_data)."""
    assert run(study, site, "launch", "--help").stdout  # the wheel answers, from outside the checkout
    launched = run(study, site, "launch", "+sweep=own_study", *SMALL_STUDY, "sweep_dir=runs/own_study",
                   "launcher.workers=1")  # one job process: each imports torch
    assert launched.returncode == 0, launched.stderr
    assert "finished: 6 ok" in launched.stdout
    assert "tank_mlp: one model per group, priced alone" in launched.stdout  # a plain module trains alone
    manifest = pq.read_table(study / "runs/own_study/manifest.parquet").to_pandas()
    assert (manifest["stackable"] == (manifest["arch"] != "tank_mlp")).all()
    assert_code_changes_are_refused_then_recorded(study, site)
    reported = run(study, site, "report", "sweep_dir=runs/own_study", *LIGHT_FITS, "figures.formats=[png]",
                   "mlflow.enabled=false")  # merge, fit, figures, report.html (MLflow: tests/test_postprocess.py)
    assert reported.returncode == 0, reported.stderr
    assert (study / "runs/own_study/report.html").stat().st_size > 0
    results = pq.read_table(study / "runs/own_study/results.parquet").to_pandas()
    assert sorted(set(results["arch"])) == ["cascade_net", "tank_mlp", "unstructured"]
    best = results.groupby("arch")["nmae"].min()
    assert (best < 0.5 * results.groupby("arch")["mean_predictor_nmae"].median()).all(), best  # each learns
    predicted = run(study, site, "predict", "sweep_dir=runs/own_study", "target=0.2", *LIGHT_FITS)
    assert predicted.returncode == 0, predicted.stderr


def assert_code_changes_are_refused_then_recorded(study: Path, site: Path) -> None:
    """The user's module edited after its rows were made: resubmit (and a launch into the sweep) refuse in one line,
    naming the pair and both hashes, and run nothing; with allow_code_change=true the task runs, and the rows say
    which code made each (issue: the edited code's rows were mixed in silently)."""
    rows = sorted((study / "runs/own_study/rows").rglob("*.parquet"))
    codes = {read_row(path)["arch"]: read_row(path)["code"] for path in rows}
    assert codes["unstructured"].startswith("nsl_hpc ") and "; system two_tank: tanks.py sha256:" in \
        codes["unstructured"] and "; arch" not in codes["unstructured"]  # the package's arch: its version says it
    assert "; arch cascade_net: tanks.py sha256:" in codes["cascade_net"]
    lost = next(path for path in rows if read_row(path)["arch"] == "cascade_net")
    lost.unlink()  # a task to run again
    with open(study / "tanks.py", "a") as module:
        module.write("# an edit after the sweep was launched\n")
    for verb, args in (("resubmit", []), ("launch", ["+sweep=own_study", *SMALL_STUDY, "launcher.workers=1"])):
        refused = run(study, site, verb, "sweep_dir=runs/own_study", *args)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
        assert refused.stderr.startswith("error: the code of two_tank/") and "changed since its rows were made" in \
            refused.stderr and "allow_code_change=true" in refused.stderr, refused.stderr
    assert not lost.exists()
    allowed = run(study, site, "resubmit", "sweep_dir=runs/own_study", "allow_code_change=true")
    assert allowed.returncode == 0 and "resubmitting 1 tasks" in allowed.stdout, allowed.stdout + allowed.stderr
    again = read_row(lost)["code"]
    assert again != codes["cascade_net"] and again.split("; ")[0] == codes["cascade_net"].split("; ")[0]


def test_a_plain_module_trains_as_the_package_trains_the_same_model(compose, cache, monkeypatch):
    """tanks.TankMLP (one MLP from (x, u) to (dx/dt, y), a plain torch.nn.Module) trained through the module stack
    gives what the package's unstructured model of that width (the same MLP, batched heads) gives: the same
    initial weights, batches, loss and Adam steps, to float32 rounding."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.setenv("NSL_HPC_CONFIG_DIR", str(EXAMPLE / "conf"))
    trained = {}
    for arch, overrides in (("tank_mlp", ()), ("unstructured", ("arch.width_factor=1.0",))):
        cfg = compose("system=two_tank", f"arch={arch}", *overrides)
        system = pair_of(cfg).system
        data, test = build_training_set(system, 0, 2.0, cache), build_test_set(system, cache)
        torch.manual_seed(0)
        model = build_model(pair_of(cfg).arch, 2, 1, width=8, depth=2)
        scaling = Scaling.fit(data, rescale_targets=False)
        member = Member(model, data, scaling, epochs=5, shuffle_seed=3)
        stack, ((snapshot,),) = train_lockstep([member], pair_of(cfg).train)
        predicted = predict_derivatives(stack, test, [scaling], torch.float32, snapshot.theta[None], [0])
        trained[arch] = (stackable(model), snapshot.outcome, predicted)
    (plain, plain_outcome, plain_predicted), (batched, outcome, predicted) = trained["tank_mlp"], \
        trained["unstructured"]
    assert (plain, batched) == (False, True)
    assert plain_outcome.steps == outcome.steps == 5 * 8  # 2,000 samples in batches of 256
    assert abs(plain_outcome.final_loss - outcome.final_loss) <= 1e-4 * outcome.final_loss
    for mine, theirs in zip(plain_predicted, predicted, strict=True):
        torch.testing.assert_close(torch.as_tensor(mine), torch.as_tensor(theirs), rtol=1e-3, atol=1e-4)


BAD_MODULE = '''
import numpy as np
from tanks import CascadeNet, TankMLP


class Leaky:
    state_dim, input_dim = 2, 1

    def __init__(self, **params):
        self.params = params

    def derivative(self, x, u):
        return np.log(x - 0.5)  # not finite where a level is 0.5 or below

    def output(self, x):
        return x[:, 1:]


class WrongShape(CascadeNet):
    def assemble(self, outputs, v, grad_energy, layout=None):
        return outputs["f"], outputs["f"]  # y of n columns, not m


class NotFinite(TankMLP):
    def __init__(self, n, m, width, depth, block, **options):  # whatever else a pair's config gives
        super().__init__(n, m, width, depth, block)

    def forward(self, z, v):
        dz, y = super().forward(z, v)
        return dz / 0.0, y
'''


MODEL_CASES = [  # (override of the own_study pair two_tank / cascade_net, the line that refuses it)
    ("system._target_=nowhere.Tank", "system/two_tank.yaml: system._target_='nowhere.Tank' does not import "
                                     "(ModuleNotFoundError: No module named 'nowhere'); put its folder on PYTHONPATH"),
    ("arch._target_=tanks.TwoTank", "arch/cascade_net.yaml: arch._target_='tanks.TwoTank' does not take (n, m, n_h, "
                                    "n_d, block, output_width): got an unexpected keyword argument 'block'"),
    ("arch._target_=bad.WrongShape", "arch/cascade_net.yaml: arch._target_='bad.WrongShape': its model gives y of "
                                     "shape (8, 2) for a batch of 8, expected (8, 1)"),
    ("arch._target_=bad.NotFinite", "arch/cascade_net.yaml: arch._target_='bad.NotFinite': its model gives a dx/dt "
                                    "that is not finite on a sample batch"),
    ("system._target_=bad.Leaky", "system/two_tank.yaml: system._target_='bad.Leaky': derivative(x, u) is not "
                                  "finite at"),
    ("system.params.area=0.0", "system/two_tank.yaml: system._target_='tanks.TwoTank': derivative(x, u) is not "
                               "finite at"),
]
RECORD_CASES = [  # (what breaks the tank_rig records, the line that refuses them)
    (lambda data: (data / "tanks_test.csv").unlink(), "tank_rig: data file data/tanks_test.csv is missing"),
    (lambda data: (data / "tanks_train.csv").write_text("t,u,level\n0,0,0\n"),
     "tank_rig: data/tanks_train.csv has no column 'y' (system.source.u, .y, .time); it has: t, u, level"),
    (lambda data: (data / "tanks_test.csv").write_text("t,u,y\n" + "".join(f"{t},0,1\n" for t in range(30))),
     "tank_rig: the test test record (tanks_test.csv) has 30 samples, not more than the system.init_samples=50"),
    (lambda data: (data / "tanks_train.csv").write_text("t,u,y\n" + "".join(f"{2 * t},0,1\n" for t in range(9))),
     "tank_rig: data/tanks_train.csv column 't' steps by 2..2 s, not system.source.sample_time_s=1"),
]


def pair_check(study: Path, monkeypatch, *selection: str) -> None:
    """The check launch runs on a (system, arch) of the user's config dir before anything is written."""
    from nsl_hpc.config import compose_config, plain
    from nsl_hpc.studies import study_of

    monkeypatch.chdir(study)
    monkeypatch.syspath_prepend(str(study))
    monkeypatch.setenv("NSL_HPC_CONFIG_DIR", str(study / "conf"))
    for module in ("tanks", "bad"):  # the copy's, not an earlier test's
        monkeypatch.delitem(sys.modules, module, raising=False)
    values = plain(compose_config(list(selection), "launch"))
    study_of(values).check_pair(pair_of(values))


@pytest.mark.parametrize(("override", "message"), MODEL_CASES)
def test_a_broken_system_or_model_is_refused_in_one_line_by_the_pair_check(study, monkeypatch, override, message):
    (study / "bad.py").write_text(BAD_MODULE)
    with pytest.raises(ConfigError) as refused:
        pair_check(study, monkeypatch, override, "system=two_tank", "arch=cascade_net")
    assert str(refused.value).startswith(message) and "\n" not in str(refused.value)


@pytest.mark.parametrize(("change", "message"), RECORD_CASES)
def test_a_broken_record_is_refused_in_one_line_by_the_pair_check(study, monkeypatch, change, message):
    change(study / "data")
    with pytest.raises(ConfigError) as refused:
        pair_check(study, monkeypatch, "study=input_output", "system=tank_rig", "arch=subnet")
    assert str(refused.value).startswith(message) and "\n" not in str(refused.value)


@pytest.mark.e2e
@pytest.mark.parametrize(("sweep", "override", "change", "message"), [
    ("own_study", MODEL_CASES[0][0], None, MODEL_CASES[0][1]),
    ("own_data", "dry_run=true", RECORD_CASES[1][0], RECORD_CASES[1][1]),
])
def test_launch_refuses_them_with_exit_2_before_anything_is_written(study, site, sweep, override, change, message):
    if change is not None:
        change(study / "data")
    refused = run(study, site, "launch", f"+sweep={sweep}", "dry_run=true", "sweep_dir=runs/refused", override)
    assert refused.returncode == 2, refused.stdout
    assert refused.stderr.startswith(f"error: {message}"), refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    assert not (study / "runs/refused").exists()


def test_records_in_npz_and_mat_files_read_as_the_same_columns_in_csv(tmp_path, monkeypatch):
    """``source.kind: files`` reads a .csv header's columns, an .npz file's arrays and a .mat file's variables
    alike: the same records, the same split."""
    from scipy.io import savemat

    from nsl_hpc.config import compose_config
    from nsl_hpc.studies.input_output.data import read_files

    monkeypatch.setenv("NSL_HPC_CONFIG_DIR", str(EXAMPLE / "conf"))
    system = pair_of(compose_config(["study=input_output", "system=tank_rig"], "one_task")).system
    system = dataclasses.replace(system, source=dataclasses.replace(system.source, data_dir=str(EXAMPLE / "data")))
    csv_train, csv_tests = read_files(system)
    for suffix in ("npz", "mat"):
        files = {}
        for name in ("tanks_train", "tanks_test"):
            columns = np.genfromtxt(EXAMPLE / "data" / f"{name}.csv", delimiter=",", names=True)
            arrays = {column: columns[column] for column in ("t", "u", "y")}
            files[name] = tmp_path / f"{name}.{suffix}"
            if suffix == "npz":
                np.savez(files[name], **arrays)
            else:
                savemat(files[name], arrays)
        source = dataclasses.replace(system.source, data_dir=str(tmp_path), train=files["tanks_train"].name,
                                     test={"test": files["tanks_test"].name})
        train, tests = read_files(dataclasses.replace(system, source=source))
        np.testing.assert_array_equal(train.y, csv_train.y)
        np.testing.assert_array_equal(tests["test"].u, csv_tests["test"].u)
