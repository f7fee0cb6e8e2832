"""Grid expansion and the manifest: the studies' 63,504 and 42,120 tasks, marginal counts, reproducible draws."""

from collections import Counter

import pytest
from omegaconf import OmegaConf

from nsl_hpc.config import compose_config
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import study_named
from nsl_hpc.studies.settings import batch_count
from nsl_hpc.sweep.grid import build_manifest, expand_grid, grid_size
from nsl_hpc.sweep.launch_settings import check_run_settings
from nsl_hpc.sweep.prepare import BuiltSweep, build_sweep, pair_configs, prepare_sweep
from nsl_hpc.sweep.task import task_id

INPUT_STATE = study_named("input_state")
INPUT_OUTPUT = study_named("input_output")
INPUT_STATE_TIERS = [2**k for k in range(1, 10)]


def grid_of(cfg) -> list | dict:
    """A launch config's sweep.grid as plain data, interpolations resolved (as its typed settings hold it)."""
    return OmegaConf.to_container(cfg.sweep.grid, resolve=True)


def built_sweep(overrides: list[str], composed: list[str] | None = None) -> BuiltSweep:
    """``build_sweep`` as launch calls it: the launch config of ``composed`` (else ``overrides``) typed once, and
    ``overrides`` as its command line."""
    return build_sweep(check_run_settings(compose_config(overrides if composed is None else composed, "launch")),
                       overrides)


def input_state_grid():
    return compose_config(["+sweep=input_state"], "launch").sweep.grid


def test_input_state_grid_has_63504_tasks_with_documented_marginals():
    grid = input_state_grid()
    tasks = list(expand_grid(grid, INPUT_STATE))
    assert len(tasks) == grid_size(grid, INPUT_STATE) == 63_504
    expected_per_value = {"system": 21_168, "arch": 21_168, "seed": 9_072, "epochs": 4_536, "data_tier": 7_056,
                          "width_tier": 15_876, "depth_tier": 31_752}
    for axis in INPUT_STATE.axes:
        counts = Counter(task[axis] for task in tasks)
        assert set(counts.values()) == {expected_per_value[axis]}, axis
    assert sorted(Counter(task["epochs"] for task in tasks)) == [2**k for k in range(1, 15)]
    assert len({tuple(task.values()) for task in tasks}) == 63_504


@pytest.fixture(scope="module")
def demo_manifest():
    cfg = compose_config(["+sweep=demo"], "launch")
    return cfg, build_manifest(cfg.sweep.grid, INPUT_STATE, pair_configs(grid_of(cfg), ["+sweep=demo"], INPUT_STATE),
                               cfg.sweep_seed)


def test_manifest_draws_are_reproducible_and_independent_of_order(demo_manifest):
    cfg, manifest = demo_manifest
    configs = pair_configs(grid_of(cfg), ["+sweep=demo"], INPUT_STATE)
    again = build_manifest(cfg.sweep.grid, INPUT_STATE, configs, cfg.sweep_seed)
    assert manifest.equals(again)
    reversed_grid = {axis: list(reversed(list(cfg.sweep.grid[axis]))) for axis in INPUT_STATE.axes}
    by_id = {row["task_id"]: row
             for row in build_manifest(reversed_grid, INPUT_STATE, configs, cfg.sweep_seed).to_pylist()}
    assert all(by_id[row["task_id"]] == row for row in manifest.to_pylist())
    other_seed = build_manifest(cfg.sweep.grid, INPUT_STATE, configs, cfg.sweep_seed + 1)
    assert other_seed["data_size"].to_pylist() != manifest["data_size"].to_pylist()


def test_manifest_ids_and_sizes_match_the_single_task_path(demo_manifest):
    """A manifest row equals what `nsl_hpc.train` with the same overrides computes."""
    _, manifest = demo_manifest
    for row in manifest.to_pylist()[::37]:
        cfg = compose_config([f"{key}={row[key]}" for key in INPUT_STATE.axes])
        assert task_id(cfg) == row["task_id"]
    draws = manifest.to_pylist()
    for row in draws:
        assert row["data_tier"] / 2 <= row["data_size"] <= row["data_tier"]
        assert row["width_tier"] // 2 <= row["width"] <= row["width_tier"]



def test_a_setting_added_later_changes_task_ids_only_away_from_its_neutral_value():
    """train.repeat=1 trains as before it existed: a sweep made then keeps its ids; another value is another task."""
    overrides = ["system=ball", "arch=input_affine", "epochs=4", "data_tier=2"]
    cfg = compose_config(overrides)
    before = OmegaConf.create(OmegaConf.to_container(cfg))
    del before.train.repeat
    assert task_id(before) == task_id(cfg) != task_id(compose_config([*overrides, "train.repeat=2"]))


def test_an_architectures_own_schedule_changes_only_its_own_task_ids():
    """train.schedule is per architecture: NARX's warmup_cosine trains as every NARX task did before the setting
    (a config stored then keeps its ids), SUBNET's schedule is in SUBNET's ids and in no NARX id."""
    narx = ["study=input_output", "system=silverbox_sim", "arch=narx"]
    subnet = ["study=input_output", "system=silverbox_sim", "arch=subnet"]
    before = OmegaConf.create(OmegaConf.to_container(compose_config(narx)))
    del before.train.schedule
    assert task_id(before) == task_id(compose_config(narx)) == task_id(
        compose_config([*narx, "train.schedule.subnet=warmup_cosine"])) != task_id(
        compose_config([*narx, "train.schedule.narx=constant"]))
    assert task_id(compose_config(subnet)) != task_id(compose_config([*subnet, "train.schedule.subnet=warmup_cosine"]))


def test_a_setting_that_changes_only_rounding_is_in_no_task_id():
    """train.rollout_segment (how a compiled SUBNET step recomputes its rollout) leaves the ids of the tasks, at
    any value and in a config stored before it existed; the learning rate does not."""
    overrides = ["study=input_output", "system=silverbox_sim", "arch=subnet"]
    cfg = compose_config(overrides)
    before = OmegaConf.create(OmegaConf.to_container(cfg))
    del before.train.rollout_segment
    ids = {task_id(compose_config([*overrides, f"train.rollout_segment.batch_major={length}"])) for length in (0, 3)}
    assert ids == {task_id(cfg)} == {task_id(before)} != {task_id(compose_config([*overrides, "train.lr=0.01"]))}


def sizes_by_all_but_epochs(rows: list[dict]) -> dict[tuple, list[tuple]]:
    """The drawn (d, n_h, n_d) of the tasks that differ only in epochs, grouped."""
    groups: dict[tuple, list[tuple]] = {}
    for row in rows:
        key = tuple(row[k] for k in INPUT_STATE.axes if k != "epochs")
        groups.setdefault(key, []).append((row["data_size"], row["width"], row["depth"]))
    return groups


@pytest.mark.slow
def test_every_input_state_task_draws_its_own_sizes():
    """Algorithm 1 draws d, n_h, n_d in its innermost loop, afresh for every epoch count: of the 63,504 tasks,
    the 4,536 sets of 14 that differ only in epochs have 14 distinct data sizes each (d is a float), so a
    (system, arch) has 7,056 distinct draws instead of 504."""
    cfg = compose_config(["+sweep=input_state"], "launch")
    rows = build_manifest(cfg.sweep.grid, INPUT_STATE, pair_configs(grid_of(cfg), ["+sweep=input_state"], INPUT_STATE),
                          cfg.sweep_seed).to_pylist()
    groups = sizes_by_all_but_epochs(rows)
    assert len(groups) == 4_536
    assert all(len({d for d, _, _ in sizes}) == 14 for sizes in groups.values())
    pair = [(row["data_size"], row["width"], row["depth"]) for row in rows
            if (row["system"], row["arch"]) == ("spring", "port_hamiltonian")]
    assert len(set(pair)) == 7_056


def test_shared_draws_keep_the_sizes_of_tasks_that_differ_only_in_epochs():
    overrides = ["+sweep=demo", "draws=shared_across_epochs"]
    cfg = compose_config(overrides, "launch")
    rows = build_manifest(cfg.sweep.grid, INPUT_STATE, pair_configs(grid_of(cfg), overrides, INPUT_STATE),
                          cfg.sweep_seed).to_pylist()
    assert all(len(set(sizes)) == 1 for sizes in sizes_by_all_but_epochs(rows).values())


@pytest.mark.parametrize(("grid_update", "message"), [
    ({"epochs": []}, "sweep.grid.epochs is empty: the grid has zero tasks"),
    ({"color": [1]}, "unknown grid axis 'color'"),
    ({"seed": [1, 1]}, "repeats a value"),
])
def test_bad_grids_are_refused(grid_update, message):
    grid = OmegaConf.to_container(input_state_grid())
    grid.update(grid_update)
    with pytest.raises(ConfigError, match=message):
        list(expand_grid(grid, INPUT_STATE))


def test_input_output_grid_has_42120_tasks_in_its_four_sub_grids():
    grid = OmegaConf.to_container(compose_config(["+sweep=input_output"], "launch").sweep.grid)
    tasks = list(expand_grid(grid, INPUT_OUTPUT))
    assert len(tasks) == grid_size(grid, INPUT_OUTPUT) == 42_120
    per_pair = Counter((task["arch"], task["system"]) for task in tasks)
    assert per_pair == {("narx", "wiener_hammerstein"): 15_552, ("narx", "silverbox"): 10_368,
                        ("subnet", "wiener_hammerstein"): 9_720, ("subnet", "silverbox"): 6_480}
    tiers = {system: sorted({t["data_tier"] for t in tasks if t["system"] == system}, reverse=True)
             for system in ("wiener_hammerstein", "silverbox")}
    assert tiers == {"wiener_hammerstein": [80000 // 2**k for k in range(9)],
                     "silverbox": [64000 // 2**k for k in range(9)]}
    multipliers = {arch: sorted({t["iter_multiplier"] for t in tasks if t["arch"] == arch})
                   for arch in ("narx", "subnet")}
    assert multipliers == {"narx": [1, *range(2, 31, 2)], "subnet": list(range(1, 13))}
    assert len({tuple(task.values()) for task in tasks}) == 42_120


def test_repro_presets_slice_both_studies_as_documented():
    """conf/sweep/repro.yaml: the 4 pairs of the published input-state laws, every data / width / depth tier,
    n_e * data_tier <= 16,384 or n_e <= 128; `repro.seeds` (interpolated into every sub-grid) sets the seeds."""
    pairs = {("ball", "input_affine"), ("ball", "port_hamiltonian"), ("spring", "input_affine"),
             ("motor", "unstructured")}
    for seeds, total in (("[0,1]", 5_376), ("[0]", 2_688)):
        grid = OmegaConf.to_container(compose_config(["+sweep=repro", f"repro.seeds={seeds}"], "launch").sweep.grid,
                                      resolve=True)
        tasks = list(expand_grid(grid, INPUT_STATE))
        assert len(tasks) == len({tuple(task.values()) for task in tasks}) == total
        assert {(task["system"], task["arch"]) for task in tasks} == pairs
        assert len({task["seed"] for task in tasks}) == len(seeds.split(","))
        kept = {(task["data_tier"], task["epochs"]) for task in tasks}
        assert kept == {(d, e) for d in INPUT_STATE_TIERS for e in (2**k for k in range(1, 15))
                        if d * e <= 16_384 or e <= 128}
    io = OmegaConf.to_container(compose_config(["+sweep=repro_io"], "launch").sweep.grid, resolve=True)
    per_pair = Counter((task["arch"], task["system"]) for task in expand_grid(io, INPUT_OUTPUT))
    assert per_pair == {("narx", "silverbox"): 2 * 9 * 6 * 2, ("narx", "wiener_hammerstein"): 7 * 6 * 3}


def test_the_subnet_and_long_epoch_presets_hold_the_slices_they_document():
    """conf/sweep/subnet_compute.yaml: every task of seed 0's Silverbox SUBNET grid below 5e9 flops (here on the
    stand-in, whose draws and counts are the same); subnet_data.yaml: one model size at every Wiener-Hammerstein
    data tier; long_epochs.yaml: ball / pH at data tier 64 to the study's 16,384 epochs."""
    stand_in = ["sweep.grid.0.system=[silverbox_sim]"]
    cut = built_sweep(["+sweep=subnet_compute"], ["+sweep=subnet_compute", *stand_in])
    whole = built_sweep(["+sweep=subnet_compute"], ["+sweep=subnet_compute", *stand_in, "sweep.max_flops=null"])
    assert whole.manifest.num_rows == 12 * 9 * 5 * 2
    below = {row["task_id"] for row in whole.manifest.to_pylist() if row["flops"] < 5e9}
    assert set(cut.manifest["task_id"].to_pylist()) == below and cut.above_max_flops > 0
    data = OmegaConf.to_container(compose_config(["+sweep=subnet_data"], "launch").sweep.grid, resolve=True)
    tasks = list(expand_grid(data, INPUT_OUTPUT))
    assert sorted(task["data_tier"] for task in tasks) == sorted(80000 // 2**k for k in range(9))
    assert {(task["width_tier"], task["depth"], task["iter_multiplier"]) for task in tasks} == {(8, 1, 1)}
    long = OmegaConf.to_container(compose_config(["+sweep=long_epochs"], "launch").sweep.grid, resolve=True)
    tasks = list(expand_grid(long, INPUT_STATE))
    assert len(tasks) == 16 and max(task["epochs"] for task in tasks) == 2**14
    assert {(task["system"], task["arch"], task["data_tier"]) for task in tasks} == {("ball", "port_hamiltonian", 64)}


def test_input_output_manifest_sizes_follow_the_draw_rules_and_the_single_task_path():
    stand_ins = [f"sweep.grid.{i}.system=[{name}_sim]"
                 for i, name in enumerate(["wiener_hammerstein", "silverbox"] * 2)]  # no measured files needed
    overrides = ["+sweep=input_output", *stand_ins, "sweep.grid.0.seed=[0]", "sweep.grid.0.iter_multiplier=[1,4]",
                 "sweep.grid.0.width_tier=[4,64]"]
    cfg = compose_config(overrides, "launch")
    grid = OmegaConf.to_container(cfg.sweep.grid)[:1]
    configs = pair_configs(grid_of(cfg), overrides, INPUT_OUTPUT)
    rows = build_manifest(grid, INPUT_OUTPUT, configs, cfg.sweep_seed).to_pylist()
    assert len(rows) == 9 * 2 * 2 * 3
    for row in rows:
        assert row["data_tier"] / 2 <= row["train_points"] <= row["data_tier"]
        assert row["width_tier"] / 2 <= row["width"] <= row["width_tier"]
        assert row["steps"] == row["iter_multiplier"] * row["train_points"]
        assert row["flops"] == row["params"] * row["steps"] * 256  # NARX: c = p n_i B
    for row in rows[::11]:
        task = compose_config(["study=input_output", *(f"{key}={row[key]}" for key in INPUT_OUTPUT.axes)])
        assert task_id(task) == row["task_id"]


def test_the_plateau_preset_holds_every_task_of_the_grid_below_its_compute_cap():
    """conf/sweep/plateau.yaml: ball / input-affine, seeds 0-1, the study's grid cut at sweep.max_flops = 3e7: the
    tasks kept are exactly those of the uncut grid below the cap."""
    cut = built_sweep(["+sweep=plateau"])
    whole = built_sweep(["+sweep=plateau"], ["+sweep=plateau", "sweep.max_flops=null"])
    assert whole.manifest.num_rows == 14 * 9 * 4 * 2 * 2 and whole.above_max_flops == 0
    below = {row["task_id"] for row in whole.manifest.to_pylist() if row["flops"] < 3e7}
    assert set(cut.manifest["task_id"].to_pylist()) == below
    assert cut.above_max_flops == whole.manifest.num_rows - len(below) > 0
    for row in cut.manifest.to_pylist():  # the paper's parameter count, 4 n_d n_h^2, in a compute column of its own
        assert row["flops_paper"] == 4 * row["depth"] * row["width"] ** 2 * row["epochs"] * row["train_points"]
        assert row["test_points"] == 100 * 1000  # test_set 100x10s
    with pytest.raises(ConfigError, match=r"sweep.max_flops=1 leaves no task of the grid"):
        built_sweep([], ["+sweep=plateau", "sweep.max_flops=1"])
    with pytest.raises(ConfigError, match=r"sweep.max_flops=-1 must be a finite number"):
        built_sweep([], ["+sweep=plateau", "sweep.max_flops=-1"])


def test_the_mechanism_slices_cap_on_either_compute_column_and_count_each_tasks_passes():
    """conf/sweep/mechanism_compute.yaml keeps the grid's tasks below its cap on the column it names (flops or the
    paper's flops_paper); with train.repeat_by_trajectories each task's steps take its own R passes per epoch."""
    for column in ("flops", "flops_paper"):
        overrides = ["+sweep=mechanism_compute", f"sweep.max_flops_column={column}"]
        cut = built_sweep(overrides)
        whole = built_sweep(overrides, [*overrides, "sweep.max_flops=null"])
        below = {row["task_id"] for row in whole.manifest.to_pylist() if row[column] < 2e7}
        assert set(cut.manifest["task_id"].to_pylist()) == below and cut.above_max_flops > 0
    with pytest.raises(ConfigError, match=r"sweep.max_flops_column='params' is not a compute column.*flops_paper"):
        built_sweep([], ["+sweep=mechanism_compute", "sweep.max_flops_column=params"])
    rule = "train.repeat_by_trajectories=[[1,50],[3,20],[10,10],[30,5]]"
    overrides = ["+sweep=mechanism_data", "sweep.grid.0.epochs=[2]", rule]
    rows = built_sweep(overrides).manifest.to_pylist()
    for row in rows:
        passes = 50 if row["n_traj"] < 3 else 20
        assert row["steps"] == row["epochs"] * batch_count(row["train_points"] * passes, 256)
    assert {row["n_traj"] >= 3 for row in rows} == {False, True}  # both rules' pairs are in the slice
    with pytest.raises(ConfigError, match="both set"):
        built_sweep([*overrides, "train.repeat=2"])


def test_an_arch_option_applies_to_the_pairs_that_have_it_and_a_relaunch_with_it_names_it(tmp_path):
    """arch.feedthrough=true on a grid of two architectures sets the input-affine pair's option only; a key no
    pair has is refused with the closest; relaunching into the sweep without it names the difference."""
    grid = ["+sweep=demo", "sweep.grid.system=[ball]", "sweep.grid.arch=[input_affine,port_hamiltonian]"]
    built = built_sweep([*grid, "arch.feedthrough=true"], grid)
    assert built.configs["ball", "input_affine"].arch.feedthrough is True
    assert not hasattr(built.configs["ball", "port_hamiltonian"].arch, "feedthrough")
    with pytest.raises(ConfigError, match=r"unknown key 'arch.feedthruogh' \(did you mean 'arch.feedthrough'\?\); "
                                          r"no \(system, arch\) of the grid has it"):
        built_sweep([*grid, "arch.feedthruogh=true"], grid)
    prepare_sweep(built_sweep(grid), tmp_path)
    with pytest.raises(ConfigError, match=r"holds a different grid \(72 tasks, this one has 72; "
                                          r"arch.feedthrough False -> True\)"):
        prepare_sweep(built, tmp_path)
