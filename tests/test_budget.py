"""Budgeted sweeps: the round rule on hand-made outcomes, and a budgeted sweep launched, stopped and relaunched
as a user would (real training, the local launcher)."""

import random

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from nsl_hpc.config import compose_config
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.budget import Budget, BudgetSettings, decide_round
from nsl_hpc.sweep.decisions import DECISION_SCHEMA, read_decisions
from nsl_hpc.sweep.launch_settings import LaunchSettings, launch_settings, planned_seconds
from nsl_hpc.sweep.rounds import Rounds, first_round_levels
from tests.sweeps import OWN_CACHE, nsl, row_files

STUDY = study_named("input_state")


def line(seed: int, width_tier: int) -> list[dict]:
    """One line's tasks (epochs 2, 4, 8) with their resources: compute grows with the epochs."""
    return [{"task_id": f"s{seed}w{width_tier}e{epochs}", "system": "ball", "arch": "unstructured", "seed": seed,
             "epochs": epochs, "data_tier": 2, "width_tier": width_tier, "depth_tier": 2, "steps": 10 * epochs,
             "params": 10 * width_tier, "flops": 1e3 * epochs * width_tier, "train_points": 100}
            for epochs in (2, 4, 8)]


def budget(seconds: float = 1e9, first_levels: int = 1, first_share: float = 0.25,
           resources: tuple[str, ...] = ("flops", "params")) -> Budget:
    """A budget of ``seconds`` of the sweep's 2e9 with the tests' rule: one level a round, margin 2."""
    settings = BudgetSettings(core_hours=None, share=None, first_levels=first_levels, first_share=first_share,
                              levels_per_round=1, margin=2.0, spread=True, round_job_minutes=30, track_laws=False,
                              stop_when=None)
    return Budget(seconds, 2e9, settings, resources, ("nmae",))


TASKS = [task for seed in (0, 1) for width_tier in (2, 4) for task in line(seed, width_tier)]
BY_ID = {task["task_id"]: task for task in TASKS}
ERRORS = {"s0w2e2": 0.10, "s1w2e2": 0.50, "s0w4e2": 0.12, "s1w4e2": 0.90}  # round 1's outcomes


def round_two(tasks: list[dict], seconds: float = 1e9, rows_order: list[str] | None = None,
              stopped: tuple[str, ...] = ()) -> list[dict]:
    rows = {task_id: {**BY_ID[task_id], "nmae": ERRORS[task_id]} for task_id in rows_order or list(ERRORS)}
    return decide_round(2, ancestors(Rounds(tasks, STUDY, 1, 1), 2, set(ERRORS)), BY_ID, rows,
                        lambda ids: 10.0 * len(ids), seconds, budget(seconds), stopped)


def ancestors(rounds: Rounds, number: int, ran: set[str]) -> dict[str, str | None]:
    """Each task of round ``number`` -> its ancestor among ``ran``, as the rounds give it to the rule."""
    return {task_id: rounds.ancestor(task_id, ran) for task_id in rounds.tasks_of(number)}


def test_rounds_follow_the_cost_axis_and_each_task_continues_its_line():
    rounds = Rounds(TASKS, STUDY, 1, 1)
    assert rounds.count == 3
    assert {rounds.round[t["task_id"]] for t in TASKS if t["epochs"] == 4} == {2}
    assert rounds.ancestor("s1w4e8", {"s1w4e2", "s1w4e4"}) == "s1w4e4" and rounds.ancestor("s1w4e2", {"s1w4e4"}) is None
    assert rounds.ancestor("s1w4e8", {"s1w4e2"}) == "s1w4e2"  # left out of round 2: back from its round-1 row


def test_round_one_takes_the_cheapest_levels_that_fit_its_share_of_the_budget_and_at_least_one():
    """4 tasks a level at 10 predicted seconds each: 40 s for the cheapest level, 80 s for two, 120 s for all."""
    def first(seconds: float, first_levels: int = 3, share: float = 0.25) -> int:
        return first_round_levels(TASKS, STUDY, budget(seconds, first_levels, share, ("flops",)),
                                  lambda ids: 10.0 * len(ids))

    assert first(400.0) == 2 and first(480.0) == 3 and first(480.0, first_levels=2) == 2
    assert first(100.0) == 1 and first(400.0, share=1.0) == 3


def test_a_round_runs_the_tasks_whose_cheaper_run_came_near_an_envelope_most_promising_first():
    decisions = {d["task_id"]: d for d in round_two(TASKS)}
    assert {t for t, d in decisions.items() if d["run"]} == {"s0w2e4", "s0w4e4"}  # within 2x of the envelope
    assert decisions["s1w4e4"]["reason"] == "far above the envelope"  # 0.90 / 2 is above 0.10 at every resource
    assert decisions["s0w2e4"]["promise"] < decisions["s0w4e4"]["promise"]
    tight = {d["task_id"]: d for d in round_two(TASKS, seconds=15.0)}  # room for one task: the most promising
    assert [t for t, d in tight.items() if d["run"]] == ["s0w2e4"] and tight["s0w4e4"]["reason"] == "budget spent"
    assert sum(d["cost_s"] for d in tight.values()) == pytest.approx(10.0)


def test_a_candidate_that_does_not_fit_is_passed_over_for_a_cheaper_one_behind_it():
    costs = {"s0w2e4": 30.0, "s0w4e4": 10.0}  # the most promising costs more than the round's 15 s

    def planned(ids):
        return sum(costs[task_id] for task_id in ids)

    rounds = Rounds(TASKS, STUDY, 1, 1)
    rows = {task_id: {**BY_ID[task_id], "nmae": error} for task_id, error in ERRORS.items()}
    decisions = {d["task_id"]: d for d in decide_round(2, ancestors(rounds, 2, set(ERRORS)), BY_ID, rows, planned,
                                                      15.0, budget(15.0))}
    assert [t for t, d in decisions.items() if d["run"]] == ["s0w4e4"] and decisions["s0w4e4"]["cost_s"] == 10.0
    assert decisions["s0w2e4"]["reason"] == "budget spent"


def test_of_equally_promising_tasks_the_one_nearer_more_envelopes_runs_first():
    """Both ancestors are on an envelope (ratio 1 / margin = 0.5): z's on compute and model size, b's on model size
    alone (compute: 1.0); with room for one task, z's line continues whatever the ids' order."""
    def task(name: str, width_tier: int, epochs: int, params: int) -> dict:
        return {"task_id": f"{name}{epochs}", "system": "ball", "arch": "unstructured", "seed": 0, "epochs": epochs,
                "data_tier": 2, "width_tier": width_tier, "depth_tier": 2, "steps": epochs, "params": params,
                "flops": float(epochs), "train_points": 100}

    tasks = [task("z", 4, 2, 10), task("z", 4, 4, 10), task("b", 2, 2, 5), task("b", 2, 4, 5)]
    by_id = {t["task_id"]: t for t in tasks}
    rows = {"z2": {**by_id["z2"], "nmae": 0.1}, "b2": {**by_id["b2"], "nmae": 0.2}}
    decided = decide_round(2, ancestors(Rounds(tasks, STUDY, 1, 1), 2, set(rows)), by_id, rows,
                           lambda ids: 10.0 * len(ids), 15.0, budget(15.0))
    assert [d["task_id"] for d in decided if d["run"]] == ["z4"]
    assert {d["task_id"]: d["promise"] for d in decided} == {"z4": 0.5, "b4": 0.5}


def test_the_planned_seconds_of_a_set_of_tasks_are_planned_once_whatever_their_order(monkeypatch):
    planned = []
    monkeypatch.setattr(LaunchSettings, "groups",
                        lambda self, tasks, saved=(): planned.append([t["task_id"] for t in tasks]) or [])
    seconds = planned_seconds(BY_ID, launch_settings(compose_config(["+sweep=demo"], "launch")))
    assert seconds(["s1w2e2", "s0w2e2"]) == seconds(["s0w2e2", "s1w2e2"]) == 0.0
    assert planned == [["s0w2e2", "s1w2e2"]]  # once, in the order of the ids


def test_a_rounds_decisions_depend_only_on_the_rows_not_on_the_order_of_tasks_or_rows():
    shuffled, rows_order = TASKS[:], list(ERRORS)
    random.Random(3).shuffle(shuffled)
    random.Random(4).shuffle(rows_order)
    assert round_two(shuffled, rows_order=rows_order) == round_two(TASKS)


# 12 tasks: spring, unstructured, 2 seeds, epochs 4 / 16 / 64 (a round each), 2 width tiers; in-process (the
# local launcher's rounds are the same loop; tests/cluster has them on SLURM).
BUDGETED = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[unstructured]", "sweep.grid.data_tier=[2]",
            "launcher=debug", "budget.first_levels=1", "budget.levels_per_round=1",
            "nsl.bootstrap=20", "nsl.max_breaks=1", "nsl.starts=6"]  # the laws tracked before each round: cheaper fits


@pytest.mark.e2e
@pytest.mark.slow
def test_a_budgeted_sweep_runs_in_rounds_skips_the_rest_and_continues_where_it_stopped(tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*BUDGETED, "budget.share=0.97", f"sweep_dir={sweep_dir}", OWN_CACHE]  # its cache: clean removes it
    first = nsl("launch", *args)
    assert first.returncode == 0, first.stderr
    assert "budget: round 1 is the 4 tasks at epochs 16, " in first.stdout  # the demo's first epochs
    decisions = read_decisions(sweep_dir)
    assert sorted({d["round"] for d in decisions}) == [1, 2, 3] and len(decisions) == 12
    ran = {d["task_id"] for d in decisions if d["run"]}
    assert 4 < len(ran) < 12  # round 1's 4 tasks and some of the later rounds'
    assert {path.stem for path in row_files(sweep_dir)} == ran
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "budget: 3 rounds decided" in status
    assert sorted(path.name for path in (sweep_dir / "budget").glob("laws-*.json")) == [
        "laws-001.json", "laws-002.json", "laws-003.json"]  # the laws before rounds 2 and 3, and after the last
    assert f"laws on the {len(ran)} rows of rounds 1-3" in status
    assert all(f"  {resource}: " in status for resource in ("compute", "data", "model"))
    merged = nsl("merge", f"sweep_dir={sweep_dir}", "compact=false")  # the rows stay files: one is removed below
    assert f"{12 - len(ran)} tasks skipped by the budget" in merged.stdout and "0 of 12 tasks" in merged.stdout

    mtimes = {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)}
    again = nsl("launch", *args)
    assert again.returncode == 0 and "every round has run" in again.stdout
    without_budget = nsl("launch", *BUDGETED[:5], f"sweep_dir={sweep_dir}")  # would run the skipped tasks
    assert without_budget.returncode != 0 and "is a budgeted sweep" in without_budget.stderr
    other_rounds = nsl("launch", *args, "budget.levels_per_round=2")  # the rounds stay as decided
    assert other_rounds.returncode != 0 and "decided with budget.levels_per_round=1" in other_rounds.stderr
    assert {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)} == mtimes  # no task ran twice

    # stopped in round 3 before its decisions were written, with one task of round 2 unfinished: the relaunch runs
    # that task alone again and decides round 3 as before
    round_three = sweep_dir / "budget" / "round-003.parquet"
    decided = pq.read_table(round_three).to_pylist()
    unfinished = next(d["task_id"] for d in decisions if d["run"] and d["round"] == 2)
    next(path for path in row_files(sweep_dir) if path.stem == unfinished).unlink()
    round_three.unlink()
    resumed = nsl("launch", *args)
    assert resumed.returncode == 0, resumed.stderr
    assert "1 to run" in resumed.stdout
    assert pq.read_table(round_three).to_pylist() == decided
    assert {path.stem for path in row_files(sweep_dir)} == ran
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0  # skipped tasks need no cache
    assert not (sweep_dir / "cache").exists() and {path.stem for path in row_files(sweep_dir)} == ran


@pytest.mark.e2e
def test_a_budget_below_the_first_round_is_refused_in_one_line_before_anything_is_written(tmp_path):
    sweep_dir = tmp_path / "sweep"
    refused = nsl("launch", *BUDGETED, "budget.share=0.05", f"sweep_dir={sweep_dir}")
    assert refused.returncode != 0
    assert refused.stderr.strip().startswith("error: the budget") and len(refused.stderr.strip().splitlines()) == 1
    assert not sweep_dir.exists()


def test_rounds_decided_before_the_resource_was_recorded_read_with_none(tmp_path):
    old_schema = pa.schema([field for field in DECISION_SCHEMA if field.name != "resource"])
    (tmp_path / "budget").mkdir()
    pq.write_table(pa.Table.from_pylist([{"task_id": "a", "round": 2, "run": True, "reason": "promising",
                                          "promise": 0.4, "cost_s": 3.0}], schema=old_schema),
                   tmp_path / "budget" / "round-002.parquet")
    assert read_decisions(tmp_path) == [{"task_id": "a", "round": 2, "run": True, "reason": "promising",
                                         "promise": 0.4, "cost_s": 3.0, "resource": None}]
