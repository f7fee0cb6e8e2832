"""How sure the laws are while a budgeted sweep's rows land: widths, budget.stop_when, and a budgeted law decided
against the full sweep's intervals."""

import json
import math

import pytest
from omegaconf import OmegaConf

from nsl_hpc.analysis.widths import decided, describe_law_records, law_state, narrowing, widths_of
from nsl_hpc.config import config_dir
from nsl_hpc.config.schema import typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.budget import BudgetSettings, StopWhen, stopped_resources
from tests.fit_clouds import law
from tests.test_budget import TASKS, round_two

FULL = law(0.01, 1.0, -0.1, (1e5, 0.2, -0.4))  # last slope -0.5, a break at 1e5


def row(fit, r_max: float = 1e7, **intervals: float) -> dict:
    """An nsl_fits row of ``fit`` with ``intervals`` (name_lo / name_hi columns)."""
    breaks = {f"{name}_{i}": value for i, (sigma, phi, delta) in enumerate(fit.breaks, start=1)
              for name, value in (("sigma", sigma), ("phi", phi), ("delta", delta))}
    return {"resource": "compute", "error": None, "b": fit.b, "alpha": fit.alpha, "beta": fit.beta,
            "delta0": fit.delta0, "margin": 0.1, "margins_by_b": json.dumps({str(fit.b): 0.1}),
            "objective": "margin", "r_max": r_max, "last_slope": fit.slopes[-1], "bootstrap": 50, **breaks,
            **intervals}


FULL_ROW = row(FULL, L_at_10x=FULL.predict(1e8), last_slope_lo=-0.6, last_slope_hi=-0.4, sigma_1_lo=5e4, sigma_1_hi=2e5,
               L_at_10x_lo=0.9 * FULL.predict(1e8), L_at_10x_hi=1.1 * FULL.predict(1e8))


def test_widths_are_those_of_the_intervals_and_infinite_without_them():
    assert widths_of(FULL_ROW) == pytest.approx({"last_slope": 0.2, "breaks": 4.0, "prediction": 1.1 / 0.9})
    assert widths_of({**FULL_ROW, "error": "too few outcomes"}) == dict.fromkeys(widths_of(FULL_ROW), math.inf)
    assert widths_of({**FULL_ROW, "bootstrap": 0}) == dict.fromkeys(widths_of(FULL_ROW), math.inf)


def test_a_budgeted_law_is_decided_when_its_slope_breaks_and_prediction_lie_inside_the_full_intervals():
    assert decided(row(law(0.01, 1.0, -0.1, (1.2e5, 0.2, -0.42)), r_max=1e6), FULL_ROW)
    assert not decided(row(law(0.01, 1.0, -0.5)), FULL_ROW)  # no break
    assert not decided(row(law(0.01, 1.0, -0.1, (1e5, 0.2, -0.7))), FULL_ROW)  # last slope -0.8
    assert not decided(row(law(0.01, 1.0, -0.1, (1e6, 0.2, -0.4))), FULL_ROW)  # the break 10x later
    assert not decided(row(law(0.03, 1.0, -0.1, (1e5, 0.2, -0.4))), FULL_ROW)  # its floor 3x higher at 10x
    assert not decided(None, FULL_ROW) and not decided({**FULL_ROW, "error": "no fit"}, FULL_ROW)


def stop_when_of(stop_when: dict | None) -> StopWhen | None:
    """``budget.stop_when`` as a launch types it: in conf/launch.yaml's budget group."""
    budget = {**OmegaConf.to_container(OmegaConf.load(config_dir() / "launch.yaml").budget), "stop_when": stop_when}
    return typed(BudgetSettings, budget, "budget").stop_when


def test_stop_when_is_checked_in_one_line():
    assert stop_when_of(None) is None
    assert stop_when_of({"last_slope": 0.2}) == StopWhen(0.2, None, None, each_resource=True)
    assert stop_when_of({"prediction": 3, "share": 0.5}).share == 0.5
    for bad, says in [({"slope": 0.2}, "budget.stop_when.slope is unknown"),
                      ({"each_resource": False}, "sets no width"),
                      ({"prediction": 0.5}, "budget.stop_when.prediction"), ({"last_slope": -1}, "last_slope"),
                      ({"last_slope": 0.2, "each_resource": "yes"}, "true or false"),
                      ({"prediction": 3, "share": 0}, "budget.stop_when.share")]:
        with pytest.raises(ConfigError, match=says):
            stop_when_of(bad)


def state(**widths: tuple[float, float]) -> list[dict]:
    """A law state: per resource name, the (last slope, prediction) widths of its laws."""
    return [{"law": f"{resource}/{i}", "resource": resource, "last_slope": slope, "prediction": prediction,
             "breaks": 1.0, "settled": True} for resource, laws in widths.items()
            for i, (slope, prediction) in enumerate(laws)]


def test_a_law_is_settled_once_it_lies_inside_the_intervals_of_its_fit_a_round_before():
    fits = [{**FULL_ROW, "system": "ball", "arch": "unstructured", "metric": "nmae", "outcomes": 40}]
    first = law_state(fits)
    assert not first[0]["settled"]  # no round before
    assert law_state(fits, first)[0]["settled"]
    moved = [{**fits[0], **row(law(0.01, 1.0, -0.1, (1e5, 0.2, -0.7)))}]  # its last slope now -0.8
    assert not law_state(moved, first)[0]["settled"]
    narrow = StopWhen(1.0, None, None, each_resource=True)
    assert narrow.narrow(law_state(fits, first)[0]) and not narrow.narrow(first[0])


def test_spending_stops_on_a_resource_once_all_its_laws_are_narrow_enough():
    columns = {"compute": "flops", "model": "params"}
    now = state(compute=[(0.1, 1.5), (0.2, 1.9)], model=[(0.1, 1.5), (0.9, 1.5)])
    each = StopWhen(0.3, None, 2.0, each_resource=True)
    assert stopped_resources(now, each, columns) == {"flops"}
    assert stopped_resources(now, StopWhen(0.3, None, 2.0, each_resource=False), columns) == set()
    assert stopped_resources(now, StopWhen(1.0, None, None, each_resource=False), columns) == {"flops", "params"}
    assert stopped_resources(now, StopWhen(0.3, None, None, each_resource=True, share=0.5), columns) == {
        "flops", "params"}  # one of model's two laws is narrow: half of them
    assert stopped_resources(now, None, columns) == set()


def test_a_round_runs_nothing_for_resources_whose_laws_are_narrow_enough():
    open_round = [d for d in round_two_with(stopped=()) if d["run"]]
    assert open_round  # the harness's round 2 runs tasks while the laws are open ...
    closed = round_two_with(stopped=("flops", "params"))
    assert not any(d["run"] for d in closed)  # ... and none once every resource's laws are narrow enough
    assert {d["reason"] for d in closed} <= {"laws narrow enough", "its ancestor did not finish"}


def round_two_with(stopped: tuple[str, ...]) -> list[dict]:
    return round_two(TASKS, stopped=stopped)


def test_status_says_how_wide_the_laws_are_and_which_resource_narrowed_most_per_core_hour():
    before = {"round": 1, "rows": 10, "committed_core_hours": {"all": 1.0, "compute": 0.0, "data": 0.0},
              "laws": state(compute=[(0.4, 4.0)], data=[(0.4, 4.0)])}
    after = {"round": 2, "rows": 30, "committed_core_hours": {"all": 3.0, "compute": 1.5, "data": 0.5},
             "laws": state(compute=[(0.2, 2.0)], data=[(0.4, 3.0)])}  # compute: each width halved for 1.5 core-h
    assert narrowing(before, after) == pytest.approx({"compute": math.log(2) / 1.5,
                                                      "data": math.log(4 / 3) / 2 / 0.5})
    lines = describe_law_records([before, after], StopWhen(0.3, None, None, each_resource=True))
    assert lines[0].startswith("laws on the 30 rows of rounds 1-2 (3 predicted core-hours)")
    assert "compute: 1 of 1 laws with intervals: last slope 0.2 (widest 0.2)" in lines[1]
    assert "1 settled, 1 narrow enough" in lines[1] and "0 narrow enough" in lines[2]
    assert "narrowed most per core-hour spent on its candidates in round 2: compute" in lines[3]
