"""The orchestration core, pure functions only (seconds: no cluster, no training): predicted times, lockstep
groups, packs and time classes, array splitting, array-id expansion, task-state classification, the sbatch
text submitit gets, and composing every config file with every command's root config."""

import shutil
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import submitit
from omegaconf import OmegaConf

from nsl_hpc.config import compose_config, config_dir, config_groups
from nsl_hpc.config.launchers import DebugLauncher, SlurmLauncher, launcher_from
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.status import remaining_seconds, running_cores, summary
from nsl_hpc.sweep.executors import array_chunks, balance, slurm_executor
from nsl_hpc.sweep.groups import GroupLock
from nsl_hpc.sweep.job import compile_allowance
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, read_manifest
from nsl_hpc.sweep.plan import (
    Group,
    Grouping,
    JobPacking,
    Pack,
    check_signal_delay,
    compiles,
    job_time,
    lockstep_groups,
    make_packs,
    padded_width,
    planned_group,
    planned_groups,
    predicted_seconds,
)
from nsl_hpc.sweep.run_settings import Cost
from nsl_hpc.sweep.slurm import expand_array_ids, merged_states, refused_flag
from nsl_hpc.sweep.submissions import record_submission
from nsl_hpc.sweep.task_states import ACCOUNTING_LAG_S, read_sweep_state, task_state
from tests.sweeps import TINY_GRID, nsl

GOLDEN = Path(__file__).parent / "golden"
COST = Cost(startup_s=2.0, group_start_s=2.0, step_seconds={"unstructured": 1e-3},
            params_per_overhead={"unstructured": 1000}, lockstep_extra={"unstructured": 0.5}, score_seconds=0.0,
            compile_s={}, compile_speedup={})  # a cost group: eager, scoring free
PACKING = JobPacking(enabled=True, short_task_minutes=5, pack_minutes=20, time_safety=3.0,
                     time_classes_minutes=(20, 60, 240))


def task(task_id: str, steps: int = 1000, width: int = 4, depth: int = 1, params: int = 100, seed: int = 0,
         epochs: int = 1) -> dict:
    return {"task_id": task_id, "system": "spring", "arch": "unstructured", "depth": depth, "width": width,
            "steps": steps, "params": params, "seed": seed, "epochs": epochs, "sweep_seed": 0}


def lockstep(size: int = 4, buckets=(2, 4, 8), model_keys=(), memory_mb: float = 1000.0,
             compile_mode="auto") -> Grouping:
    return Grouping(size, tuple(buckets), memory_mb, tuple(model_keys), compile_mode)


def planned(tasks: list[dict], *overrides: str) -> list[Pack]:
    """The jobs the launch config of ``overrides`` plans for ``tasks``."""
    return launch_settings(compose_config(list(overrides), "launch")).plan(tasks)


def test_predicted_seconds_follow_the_cost_model():
    assert predicted_seconds("unstructured", 1000, 1000, COST) == pytest.approx(2.0 + 1000 * 1e-3 * 2)


def test_time_limit_is_the_smallest_class_holding_the_safety_margin_and_too_long_is_one_line():
    assert job_time(6 * 60, PACKING) == (20, 1)  # 18 min with safety 3
    assert job_time(7 * 60, PACKING) == (60, 1)  # 21 min
    assert job_time(80 * 60, PACKING) == (240, 1)
    with pytest.raises(ConfigError, match=r"more than the largest of packing\.time_classes_minutes"):
        job_time(81 * 60, PACKING)


def test_slurm_warning_must_leave_start_up_time_in_the_shortest_job():
    check_signal_delay(120, [60, 240])
    check_signal_delay(25, [1])  # sent 25-55 s before the end of a 60 s job: at least 5 s after its start
    with pytest.raises(ConfigError, match=r"signal_delay_s=45 leaves no start-up time in a 1-minute job.*at most 25"):
        check_signal_delay(45, [1, 60])


def test_widths_pad_to_their_bucket_and_groups_never_mix_keys_or_exceed_k():
    assert [padded_width(w, [2, 4, 8]) for w in (1, 2, 3, 5, 8, 9)] == [2, 2, 4, 8, 8, 9]
    tasks = [task(f"t{i}", width=w, depth=d, steps=100 * i)
             for i, (w, d) in enumerate((w, d) for w in (1, 2, 3, 4, 5) for d in (1, 2) for _ in range(3))]
    groups = lockstep_groups(tasks, lockstep(size=4))
    assert sorted(t["task_id"] for g in groups for t in g) == sorted(t["task_id"] for t in tasks)
    for group in groups:
        assert len(group) <= 4
        assert len({(t["depth"], padded_width(t["width"], [2, 4, 8])) for t in group}) == 1
    assert len(groups) == 10  # (depth 2) x (buckets 2: 6 tasks, 4: 6 tasks, 8: 3 tasks) -> 2 + 2 + 1 each
    assert all(len(g) == 1 for g in lockstep_groups(tasks, lockstep(size=1)))


def test_a_group_predicted_longer_than_allowed_is_halved_until_it_fits_or_holds_one_model():
    """8 models of 1,000 steps (1.1 ms a step alone, 0.5 of that per further model): the group of 8 takes
    2 + 1.1 * 4.5 = 6.95 s; with 5 s allowed it is halved into 4 + 4 (2 + 1.1 * 2.5 = 4.75 s each)."""
    tasks = [task(f"t{i}", steps=1000) for i in range(8)]
    whole = planned_groups(tasks, lockstep(size=8), COST)
    assert [len(group.task_ids) for group in whole] == [8] and whole[0].seconds == pytest.approx(6.95)
    halved = planned_groups(tasks, lockstep(size=8), COST, longest_s=5.0)
    assert [group.task_ids for group in halved] == [tuple(f"t{i}" for i in range(k, k + 4)) for k in (0, 4)]
    assert all(group.seconds == pytest.approx(4.75) for group in halved)
    alone = planned_groups(tasks, lockstep(size=8), COST, longest_s=1.0)  # too long even alone: one model each
    assert sorted(len(group.task_ids) for group in alone) == [1] * 8


def test_a_job_pays_its_start_up_once_whatever_its_groups_and_only_on_slurm():
    (pack,) = make_packs([Group(("a",), 10.0), Group(("b",), 20.0)], PACKING, startup_s=2.0)
    assert pack.seconds == 32.0
    tasks = [task(f"t{i}", steps=1000 + i, width=1 + i % 16, depth=1 + i % 3) for i in range(50)]
    plans = {launcher: planned(tasks, "+sweep=demo", f"launcher={launcher}", "cost.startup_s=100",
                               "packing.enabled=false") for launcher in ("local", "slurm")}
    assert [p.task_ids for p in plans["slurm"]] == [p.task_ids for p in plans["local"]]
    assert all(job.seconds == pytest.approx(alone.seconds + 100)
               for job, alone in zip(plans["slurm"], plans["local"], strict=True))


def test_groups_fill_from_the_longest_models_down():
    """33 models in groups of up to 32: the 32 longest train together and the shortest alone (filled from the
    shortest up, the longest would run alone for the longest time); groups and their models ascend by steps."""
    tasks = [task(f"t{i}", steps=10 + i) for i in range(33)]
    groups = lockstep_groups(tasks[::-1], lockstep(size=32))
    assert [[t["task_id"] for t in g] for g in groups] == [["t0"], [f"t{i}" for i in range(1, 33)]]


def test_a_group_holds_no_more_models_than_its_largest_fits_in_the_memory_budget():
    """Models of 100 MB (steps 0..5) then 300 MB (6..9) in a 1,000 MB budget, filled from the longest: 3 of
    300 MB, then t6 with two of 100 MB (3 x 300 MB), then the rest; a model larger than the budget still trains
    (alone)."""
    tasks = [{**task(f"t{i}", steps=i), "train_memory_mb": 100.0 if i < 6 else 300.0} for i in range(10)]
    groups = lockstep_groups(tasks, lockstep(size=32, memory_mb=1000))
    assert [[t["task_id"] for t in g] for g in groups] == [["t0", "t1", "t2", "t3"], ["t4", "t5", "t6"],
                                                          ["t7", "t8", "t9"]]
    huge = [{**task("big"), "train_memory_mb": 5000.0}]
    assert [[t["task_id"] for t in g] for g in lockstep_groups(huge, lockstep(memory_mb=1000))] == [["big"]]


def test_milestone_tasks_of_one_model_stay_in_one_group_and_cost_their_longest_run():
    tasks = [task(f"s{seed}e{epochs}", steps=100 * epochs, seed=seed, epochs=epochs)
             for seed in range(3) for epochs in (1, 2, 4)]
    groups = lockstep_groups(tasks, lockstep(size=2, model_keys=["seed"]))
    assert sorted(len(g) for g in groups) == [3, 6]  # 2 models of 3 tasks, then 1 model
    for group in groups:
        assert len({t["seed"] for t in group}) == len(group) // 3
    one = [t for t in tasks if t["seed"] == 0]
    per_step = predicted_seconds("unstructured", 1, 100, COST) - COST.startup_s
    assert planned_group(one, COST, lockstep(model_keys=["seed"])).seconds == pytest.approx(2.0 + 400 * per_step)


def test_a_group_compiles_where_the_predicted_saving_exceeds_the_compile_time():
    """A compiled step 1.5x faster saves a third of a group's eager training seconds: with 20 s to compile, a
    group of 98 training seconds (100 with the 2 s start-up) compiles (saves 33 s; planned at 2 + 98 / 1.5 + 20),
    one of 48 s does not (16 s), nor one of 59.5 s (19.8 s; with the start-up it would have been 20.5 s): the
    start-up counts toward neither; always and never override, and under auto
    an architecture without a measured speedup never compiles."""
    cost = replace(COST, compile_s={"unstructured": 20.0}, compile_speedup={"unstructured": 1.5})
    per_step = predicted_seconds("unstructured", 1, 100, COST) - COST.startup_s
    long, short = [task("long", steps=round(98 / per_step))], [task("short", steps=round(48 / per_step))]
    (planned,) = planned_groups(long, lockstep(), cost)
    assert planned.compiled and planned.seconds == pytest.approx(2 + 98 / 1.5 + 20, rel=1e-3)
    assert not planned_groups(short, lockstep(), cost)[0].compiled
    assert not planned_groups([task("edge", steps=round(59.5 / per_step))], lockstep(), cost)[0].compiled
    assert planned_groups(short, lockstep(compile_mode="always"), cost)[0].compiled
    assert not planned_groups(long, lockstep(compile_mode="never"), cost)[0].compiled
    (unmeasured,) = planned_groups(long, lockstep(compile_mode="always"), COST)  # no speedup, no compile time
    assert unmeasured.compiled and unmeasured.seconds == pytest.approx(100.0, rel=1e-3)
    assert compiles("unstructured", 100.0, cost, "auto") and not compiles("narx", 1e9, cost, "auto")
    assert not compiles("narx", 1e9, replace(cost, compile_speedup={"narx": None}), "auto")


def test_a_compiled_group_may_go_without_a_heartbeat_three_times_its_compile_time_longer():
    launch = compose_config(["+sweep=input_output", "cost.compile_s.subnet=400", "cost.compile_s.narx=null",
                             "cost.compile_speedup.narx=null"], "launch")
    settings = launch_settings(launch)
    assert compile_allowance(settings, "subnet") == 1200.0 and compile_allowance(settings, "narx") == 0.0


def test_a_groups_seconds_charge_the_extra_share_while_more_models_train():
    tasks = [task("a", steps=100), task("b", steps=300)]
    per_step = predicted_seconds("unstructured", 1, 100, COST) - COST.startup_s
    expected = 2.0 + 100 * per_step * 1.5 + 200 * per_step
    assert planned_group(tasks, COST, lockstep()).seconds == pytest.approx(expected)


def test_a_groups_seconds_charge_scoring_each_task_on_its_test_set():
    """A test set of 1e6 samples costs each task of 100 parameters 0.1 s at 1e-9 s per sample and parameter (the
    100x100s test set froze 81 of 779 small tasks when the planner left scoring out)."""
    tasks = [{**task("a", steps=100), "test_points": 1_000_000}, {**task("b", steps=300), "test_points": 1_000_000}]
    unscored = planned_group([task("a", steps=100), task("b", steps=300)], COST, lockstep()).seconds
    scored = planned_group(tasks, replace(COST, score_seconds=1e-9), lockstep()).seconds
    assert scored == pytest.approx(unscored + 2 * 0.1)
    assert planned_group(tasks, COST, lockstep()).seconds == pytest.approx(unscored)  # a run.yaml from before


def test_packs_carry_whole_groups_short_ones_fill_packs_long_ones_run_alone():
    groups = [Group((f"s{i}a", f"s{i}b"), 60.0) for i in range(50)] + [Group(("long",), 10 * 60.0)]
    packs = make_packs(groups, PACKING)
    assert sorted(g.task_ids for p in packs for g in p.groups) == sorted(g.task_ids for g in groups)  # whole, once
    long = [p for p in packs if p.groups == (Group(("long",), 600.0),)]
    assert len(long) == 1 and long[0].time_limit_min == 60
    short = [p for p in packs if p not in long]
    assert [len(p.groups) for p in short] == [20, 20, 10]  # 20 min of 1-min groups per pack
    assert all(p.seconds == sum(g.seconds for g in p.groups) for p in packs)
    assert short[0].task_ids[:3] == ("s0a", "s0b", "s1a")
    assert len(make_packs(groups, replace(PACKING, enabled=False))) == len(groups)


def test_plan_jobs_packs_for_slurm_only_and_stretches_time_limits():
    tasks = [task(f"t{i}", steps=1000 + i, width=1 + i % 16, depth=1 + i % 3) for i in range(200)]
    slurm = planned(tasks, "+sweep=demo", "launcher=slurm")
    assert sorted(t for p in slurm for t in p.task_ids) == sorted(t["task_id"] for t in tasks)
    assert len(slurm) < sum(len(p.groups) for p in slurm)  # short groups share jobs
    local = planned(tasks, "+sweep=demo")
    assert all(len(p.groups) == 1 for p in local)
    stretched = launch_settings(compose_config(["+sweep=demo", "launcher=slurm"], "launch")).plan(tasks,
                                                                                                 time_factor=100)
    assert max(p.time_limit_min for p in stretched) > max(p.time_limit_min for p in slurm)


def test_arrays_split_by_time_limit_and_size():
    packs = [Pack((Group((f"t{i}",), 1.0),), 1.0, limit) for i, limit in enumerate([20] * 5 + [60] * 2)]
    chunks = array_chunks(packs, max_array_size=2)
    assert [[p.time_limit_min for p in c] for c in chunks] == [[20, 20], [20, 20], [20], [60, 60]]


def test_local_workers_get_whole_groups_of_about_equal_time():
    packs = make_packs([Group((f"t{i}",), float(i + 1)) for i in range(10)], PACKING)
    shares = balance(packs, workers=3)
    assert len(shares) == 3
    assert sorted(g.task_ids for share in shares for g in share) == [(f"t{i}",) for i in sorted(map(str, range(10)))]
    loads = [sum(g.seconds for g in share) for share in shares]
    assert max(loads) - min(loads) <= 10  # 55 s over 3 workers: greedy longest-first


@pytest.mark.parametrize(("job_id", "elements"), [
    ("12", ["12"]), ("12_3", ["12_3"]), ("12_[0-2,5%4]", ["12_0", "12_1", "12_2", "12_5"]), ("7_[4]", ["7_4"]),
])
def test_array_ids_expand(job_id, elements):
    assert expand_array_ids(job_id) == elements


@pytest.mark.parametrize(("row", "failure", "element", "element_state", "age", "state"), [
    ("done", {"time": 5.0, "status": "failed"}, "1_0", "FAILED", 100, "done"),
    ("corrupt", None, "1_0", "COMPLETED", 100, "corrupt"),
    ("missing", {"time": 5.0, "status": "frozen"}, "1_0", "RUNNING", 100, "frozen"),  # recorded after submission
    ("missing", {"time": -5.0, "status": "failed"}, "1_0", "RUNNING", 100, "running"),  # an older attempt's
    ("missing", None, "1_0", "PENDING", 100, "pending"),
    ("missing", None, "1_0", "REQUEUED", 100, "pending"),
    ("missing", None, "1_0", None, 1, "missing"),  # the queue answered without it: cancelled, whatever sacct lags
    ("missing", None, "1_0", "CANCELLED", 100, "missing"),
    ("missing", None, None, None, 0, "missing"),  # never submitted
])
def test_task_states_are_classified(row, failure, element, element_state, age, state):
    assert task_state(row, failure, element, 0.0, element_state, now=age) == state


@pytest.mark.parametrize(("age", "state"), [(1, "pending"), (ACCOUNTING_LAG_S + 1, "missing")])
def test_without_the_queue_a_just_submitted_element_is_pending_for_the_accounting_lag(age, state):
    assert task_state("missing", None, "1_0", 0.0, None, now=age, queue_answered=False) == state


def test_the_queue_is_the_truth_for_what_has_not_ended():
    """sacct's PENDING for an element squeue no longer holds is a stale record (slurmdbd restarted, lagging)."""
    accounted = {"7_0": "PENDING", "7_1": "COMPLETED", "7_2": "RUNNING", "8_0": "CANCELLED"}
    queued = {"7_2": "RUNNING", "9_0": "PENDING"}  # 9: another sweep's job
    assert merged_states(accounted, queued, {"7", "8"}) == {"7_1": "COMPLETED", "7_2": "RUNNING", "8_0": "CANCELLED"}
    assert merged_states(accounted, None, {"7", "8"}) == accounted


def test_launchers_are_schemas_and_a_wrong_one_is_one_line():
    assert launcher_from({"name": "debug"}) == DebugLauncher()
    slurm = launcher_from(OmegaConf.create({"name": "slurm", "partition": "cpu", "hold": True}))
    assert isinstance(slurm, SlurmLauncher) and slurm.partition == "cpu" and slurm.mem == "2G" and slurm.hold
    with pytest.raises(ConfigError, match=r"launcher\.name=.pbs. is unknown"):
        launcher_from({"name": "pbs"})
    with pytest.raises(ConfigError, match=r"launcher\.nodes is unknown; launcher has: name, partition"):
        launcher_from({"name": "slurm", "nodes": 2})


def test_the_sbatch_text_of_a_typical_array_is_the_recorded_one(monkeypatch):
    """Like submitit's own recorded sbatch test: what sbatch gets for an array of 3 packs of 60 minutes. The text
    needs no cluster; submitit's executor refuses to be built where srun is not installed (a laptop): there it is
    told srun's affinity, as on a cluster."""
    if shutil.which("srun") is None:
        monkeypatch.setattr(submitit.SlurmExecutor, "affinity", classmethod(lambda cls: 2))
    launcher = SlurmLauncher(partition="cpu", account="nsl", setup=["module load python"],
                             extra_sbatch={"constraint": "intel"})
    executor = slurm_executor(Path("/sweeps/demo"), 60, launcher, "demo")
    executor.parameters["map_count"] = 3
    text = executor._make_submission_file_text(executor._submitit_command_str, "UID")
    text = text.replace(sys.executable, "PYTHON")
    assert text == (GOLDEN / "slurm_array.sbatch").read_text()


ROOTS = sorted(path.stem for path in config_dir().glob("*.yaml"))


@pytest.mark.parametrize("root", ROOTS)
def test_every_command_root_config_composes(root):
    required = sorted(OmegaConf.missing_keys(OmegaConf.load(config_dir() / f"{root}.yaml")))
    cfg = compose_config([f"{key}=x" for key in required], root)
    assert all(cfg[key] == "x" for key in required)


@pytest.mark.parametrize(("group", "option"), [(group, option) for group, options in config_groups().items()
                                               for option in options])
def test_every_config_file_composes_with_the_root_config_that_uses_it(group, option):
    """Each option of each group, in the root config that has the group (a system or arch with its study)."""
    root = "report" if group in ("nsl", "figures") else "launch"
    override = f"+sweep={option}" if group == "sweep" else f"{group}={option}"
    extra = ["sweep_dir=x"] if root == "report" else [] if group == "sweep" else ["+sweep=demo"]
    path = config_dir() / group / f"{option}.yaml"
    study = OmegaConf.load(path).get("study") if path.exists() and group in ("system", "arch") else None
    cfg = compose_config([override, *extra, *([f"study={study}"] if study else [])], root)
    if group == "test_set":  # placed in system.test_set
        assert cfg.system.test_set == OmegaConf.load(path)
        return
    chosen = cfg.sweep if group == "sweep" else cfg[group]
    if "name" in chosen:
        assert chosen.name == option


def test_status_time_left_is_the_planned_groups_work_over_the_cores_training(tmp_path):
    """3 models of one lockstep group (depth 1, widths 2-3 in one bucket), a step costing 1000 s alone and half of
    that more per further model still training: by hand, 1000 s x (2 s1 + 1.5 (s2 - s1) + (s3 - s2)) for steps
    s1 <= s2 <= s3; over the cores that train (a job per core), not over the tasks (before: each task's cost
    alone, divided by the running tasks, ~32x too optimistic for a group of 32)."""
    sweep_dir = tmp_path / "sweep"
    cost = ["cost.group_start_s=0", "cost.step_seconds.input_affine=1000", "cost.params_per_overhead.input_affine=1e12",
            "cost.lockstep_extra.input_affine=0.5", "cost.score_seconds=0"]
    grid = [*TINY_GRID, "sweep.grid.seed=[3]", "sweep.grid.epochs=[2,4,8]"]  # the later values win
    assert nsl("launch", *grid, *cost, "lockstep.width_buckets=[4]", "compile=never", "launcher=debug",
               f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    manifest = read_manifest(sweep_dir)
    assert set(manifest["depth"].to_pylist()) == {1} and max(manifest["width"].to_pylist()) <= 4  # one group
    s1, s2, s3 = sorted(manifest["steps"].to_pylist())
    by_hand = 1000 * (2 * s1 + 1.5 * (s2 - s1) + (s3 - s2))
    state = read_sweep_state(sweep_dir)
    launch = launch_settings(read_launch_config(sweep_dir))
    assert remaining_seconds(sweep_dir, state, launch) == pytest.approx(by_hand, rel=1e-6)
    assert running_cores(sweep_dir, state) == 0
    lock = GroupLock(sweep_dir, ["a", "group", "trained", "now"])
    assert lock.acquire() is None
    assert running_cores(sweep_dir, state) == 1
    assert f"ETA {by_hand / 3600 / 2:.1f} h on 2 cores running" in summary(state, by_hand, 2)
    assert f"{by_hand / 3600:.1f} core-hours left" in summary(state, by_hand, 0)
    # submitted, the tasks are what their array element was predicted to take at submission: no planning again
    # (the queue of a machine with SLURM holds no job 7: its tasks are missing either way)
    record_submission(sweep_dir, "7", 60, ["7_0"], [manifest["task_id"].to_pylist()], [[2 * by_hand / 3] * 3])
    state = read_sweep_state(sweep_dir, queue_required=False)  # it reads the submissions (and SLURM's queue, where
    assert remaining_seconds(sweep_dir, state, launch) == pytest.approx(2 * by_hand)


def test_a_packs_tasks_share_their_own_groups_prediction_and_the_jobs_start():
    """A group of 8 tasks and a lone task, 100 s each, and 9 s of job start: a task of the 8 is predicted 100/8 + 1 s,
    the lone one 100 + 1 s (an equal share of the pack, 23.3 s each, would call the lone one nearly done)."""
    pack = Pack((Group(tuple(f"t{i}" for i in range(8)), 100.0), Group(("lone",), 100.0)), 209.0, 10)
    assert pack.task_seconds() == pytest.approx([100 / 8 + 1] * 8 + [101.0])
    assert sum(pack.task_seconds()) == pytest.approx(pack.seconds)


@pytest.mark.parametrize(("message", "flags", "flag"), [
    ("sbatch: error: Invalid feature specification", ["constraint", "gres"], "constraint"),
    ("sbatch: error: Invalid generic resource (gres) specification", ["constraint", "gres"], "gres"),
    ("sbatch: unrecognized option '--no-such-flag=1'", ["exclusive", "no_such_flag"], "no_such_flag"),
    ("sbatch: error: Batch job submission failed: Requested node configuration is not available", ["reservation"],
     "reservation"),
    ("sbatch: error: Batch job submission failed: something else", ["a", "b"], None)])
def test_a_refused_sbatch_flag_is_named_where_the_refusal_tells_which(message, flags, flag):
    assert refused_flag(message, flags) == flag
