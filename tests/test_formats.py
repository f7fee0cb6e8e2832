"""A sweep directory's format: launch.yaml records it, a format-1 sweep (written before the settings added since)
is upgraded as it is read and runs as it ran, and a later format is refused in one line (one sweep for all)."""

import pytest
import yaml

from nsl_hpc.sweep.formats import FORMAT, FORMAT_1_SETTINGS
from nsl_hpc.sweep.manifest import read_launch_config
from nsl_hpc.sweep.rows import read_row
from tests.sweeps import nsl, row_files

pytestmark = pytest.mark.e2e  # launches and resubmits a sweep (make test-fast leaves it out)

TINY = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[unstructured]", "sweep.grid.data_tier=[2]",
        "sweep.grid.epochs=[4]", "sweep.grid.width_tier=[2]", "sweep.grid.depth_tier=[2]", "launcher=debug"]


def outcome(path) -> tuple:
    row = read_row(path)
    return row["nmae"], row["nmse"], row["final_loss"], row["params"], row["flops"]


def without(path, keys) -> None:
    """Remove the dotted ``keys`` (and ``format``) from the YAML file at ``path``, as a format-1 sweep wrote it."""
    values = yaml.safe_load(path.read_text())
    values.pop("format", None)
    for key in keys:
        *parents, leaf = key.split(".")
        node = values
        for parent in parents:
            node = node.get(parent, {})
        node.pop(leaf, None)
    path.write_text(yaml.safe_dump(values))


def test_a_format_1_sweep_is_upgraded_and_runs_as_it_ran_and_a_later_format_is_refused(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY, f"sweep_dir={sweep_dir}").returncode == 0
    assert yaml.safe_load((sweep_dir / "launch.yaml").read_text())["format"] == FORMAT
    rows = {path.name: outcome(path) for path in row_files(sweep_dir)}
    assert len(rows) == 2

    keys = [key for key, _ in FORMAT_1_SETTINGS]
    for name in ("launch.yaml", "run.yaml"):
        without(sweep_dir / name, keys)
    without(sweep_dir / "configs" / "spring__unstructured.yaml", ["system._target_", "arch._target_"])  # before targets
    launch = read_launch_config(sweep_dir)
    assert launch["format"] == FORMAT and launch["checkpoint"]["every_minutes"] == 0 and launch["compile"] == "auto"
    assert launch["cost"]["compile_s"] == {} and launch["metric"]["normalization"] is None and launch["threads"] == 1
    assert "done 2" in nsl("status", f"sweep_dir={sweep_dir}").stdout

    lost = row_files(sweep_dir)[0]
    lost.unlink()
    resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert resubmitted.returncode == 0, resubmitted.stderr
    assert outcome(lost) == rows[lost.name]  # trained again as it was, from its config and seed
    merged = nsl("merge", f"sweep_dir={sweep_dir}")
    assert merged.returncode == 0 and "merged 2 tasks" in merged.stdout

    values = yaml.safe_load((sweep_dir / "launch.yaml").read_text())  # then a later nsl_hpc writes format 3
    (sweep_dir / "launch.yaml").write_text(yaml.safe_dump({**values, "format": FORMAT + 1}))
    for verb in ("status", "resubmit", "launch"):
        refused = nsl(verb, *(TINY if verb == "launch" else ()), f"sweep_dir={sweep_dir}")
        assert refused.returncode == 2, (verb, refused.stdout)
        assert refused.stderr.strip().endswith("upgrade nsl_hpc to work on this sweep")
        assert len(refused.stderr.strip().splitlines()) == 1
