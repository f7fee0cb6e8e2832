"""The nMSE tail of the compute-nMSE envelope (conf/nmse_tail.yaml): the models on and near the envelope of a merged
input-state sweep, trained again, their squared error decomposed by time within a test trajectory, by samples of
large |dx/dt| and by column, and their nMSE on other test sets, set beside the published compute-nMSE law. Writes
the tables to ``output`` and prints them.

    python benchmarks/nmse_tail.py [sweep_dir=runs/repro/input_state] [near=1.5]
"""

import dataclasses
import itertools
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import torch

from nsl_hpc.analysis.published import published_law, step_envelope_at
from nsl_hpc.analysis.reproduction import factor_text, resource_text
from nsl_hpc.config import compose_config, plain, tool_settings
from nsl_hpc.config.schema import typed
from nsl_hpc.config.system import InputStateSystem, TestSet
from nsl_hpc.core.atomic import write_text
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.studies.input_state.data import Dataset, build_test_set
from nsl_hpc.studies.input_state.lockstep import predict_derivatives, train_lockstep
from nsl_hpc.studies.input_state.study import InputState
from nsl_hpc.studies.metrics import spreads
from nsl_hpc.sweep.job import TaskConfigs
from nsl_hpc.sweep.manifest import read_manifest


def settings(argv: list[str]) -> dict[str, Any]:
    return plain(tool_settings("nmse_tail", argv))


def near_envelope(rows: Sequence[Mapping[str, Any]], cfg: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """The rows within ``near`` of the running nMSE envelope, inside the ``flops`` range, by flops."""
    rows = sorted(rows, key=lambda row: row["flops"])
    r = np.array([row["flops"] for row in rows])
    e = np.array([row["nmse"] for row in rows])
    envelope = step_envelope_at(r, e, r)
    low, high = cfg["flops"]
    return [row for row, error, best in zip(rows, e, envelope, strict=True)
            if low <= row["flops"] <= high and error <= cfg["near"] * best]


def trained_again(sweep_dir: Path, task: Mapping[str, Any]) -> tuple[Any, Any, Any]:
    """(stack, theta (1, P), scaling) of the manifest row ``task`` trained again, alone."""
    resolved = TaskConfigs(sweep_dir).of(task).task
    member = InputState().member(resolved, [task["epochs"]])
    stack, snapshots = train_lockstep([member], resolved.pair.train)
    return stack, snapshots[0][-1].theta[None], member.scaling


def squared_shares(error: np.ndarray, test: Dataset, points: int, cfg: Mapping[str, Any]) -> dict[str, float]:
    """Shares of the normalised squared error (e / sigma_j)^2 summed: by time within a trajectory, by samples whose
    |dx/dt| exceeds ``outlier_sigma`` sigma_j in some column, and by column."""
    sigma = spreads(test.dx)["scalar"]
    squared = np.square(error / sigma)
    total = squared.sum()
    t = (np.arange(len(error)) % points) * cfg["dt_s"]
    bins = cfg["time_bins_s"]
    shares = {f"t {low:g}-{high:g} s": float(squared[(t >= low) & (t < high)].sum() / total)
              for low, high in itertools.pairwise(bins)}
    column_sigma = test.dx.std(axis=0, ddof=1)
    outliers = (np.abs(test.dx - test.dx.mean(axis=0)) > cfg["outlier_sigma"] * column_sigma).any(axis=1)
    shares[f"|dx/dt| > {cfg['outlier_sigma']:g} sigma ({outliers.mean():.2%} of samples)"] = float(
        squared[outliers].sum() / total)
    shares |= {f"column x{j + 1}": float(squared[:, j].sum() / total) for j in range(error.shape[1])}
    return shares


def scores(error: np.ndarray, test: Dataset, keep: np.ndarray) -> tuple[float, float]:
    """nMAE and nMSE (one spread of the kept targets, the authors' normalisation) of the kept samples."""
    sigma = test.dx[keep].std(ddof=1)
    return float(np.abs(error[keep]).mean() / sigma), float(np.square(error[keep]).mean() / sigma**2)


def main() -> None:
    cfg = settings(sys.argv[1:])
    sweep_dir = Path(cfg["sweep_dir"])
    results = pq.read_table(sweep_dir / "results.parquet").to_pylist()
    rows = [row for row in results if (row["system"], row["arch"], row["status"]) == (cfg["system"], cfg["arch"], "ok")]
    chosen = near_envelope(rows, cfg)
    manifest = {task["task_id"]: task for task in read_manifest(sweep_dir).to_pylist()}
    torch.set_num_threads(1)
    system = TaskConfigs(sweep_dir).of(manifest[chosen[0]["task_id"]]).task.pair.system
    cfg["dt_s"] = system.simulation.dt_s
    tests = test_sets(system, cfg, ArrayCache(sweep_dir / "cache"))
    measured = []
    for row in chosen:
        stack, theta, scaling = trained_again(sweep_dir, manifest[row["task_id"]])
        entry = {"row": row, "scores": {}}
        for name, (test, points) in tests.items():
            error = predict_derivatives(stack, test, [scaling], torch.float32, theta, [0])[0] - test.dx
            entry["scores"][name] = scores(error, test, np.ones(len(test), dtype=bool))
            if name == "default":
                entry["shares"] = squared_shares(error, test, points, cfg)
                after = (np.arange(len(test)) % points) * cfg["dt_s"] >= cfg["transient_s"]
                entry["scores"]["default, transients left out"] = scores(error, test, after)
        measured.append(entry)
        print(f"{row['task_id']}: flops {row['flops']:.2g}, row nMSE {row['nmse']:.3g}, again "
              f"{entry['scores']['default'][1]:.3g}", flush=True)
    text = tables(measured, cfg)
    write_text(text, Path(cfg["output"]))
    print(text)


def test_sets(system: InputStateSystem, cfg: Mapping[str, Any], cache: ArrayCache
              ) -> dict[str, tuple[Dataset, int]]:
    """The system's test set ('default') and each of ``test_sets``, with their samples per trajectory."""
    specs = {"default": system.test_set}
    for name in cfg["test_sets"]:
        specs[name] = typed(TestSet, compose_config([f"system={cfg['system']}", f"test_set={name}"]).system.test_set,
                            "system.test_set")
    return {name: (build_test_set(dataclasses.replace(system, test_set=spec), cache),
                   round(spec.duration_s / cfg["dt_s"])) for name, spec in specs.items()}


def spread_text(values: Sequence[float], form: str) -> str:
    """'median (10th-90th percentile)' of ``values``."""
    low, median, high = np.percentile(values, [10, 50, 90])
    return f"{median:{form}} ({low:{form}}-{high:{form}})"


def tables(measured: Sequence[Mapping[str, Any]], cfg: Mapping[str, Any]) -> str:
    """The decomposition per model and the envelopes over the law per scoring."""
    key = (cfg["system"], cfg["arch"], "compute", "nmse")
    shares = list(measured[0]["shares"])
    lines = [f"**Where the squared error lies** ({cfg['system']} / {cfg['arch']}: the {len(measured)} models within "
             f"{cfg['near']:g}x of the nMSE envelope between {resource_text(cfg['flops'][0])} and "
             f"{resource_text(cfg['flops'][1])} flops, "
             "trained again; shares of the sum of (e / sigma)^2 on the default test set; a row per model on the "
             "envelope, then the median and the 10-90% range of all)", "",
             "| flops | nMSE (row / again) | nMSE / nMAE^2 | " + " | ".join(shares) + " |",
             "|---:|---|---:|" + "---:|" * len(shares)]
    best = np.inf
    for entry in measured:
        row, (nmae, nmse) = entry["row"], entry["scores"]["default"]
        if nmse < best:
            best = nmse
            lines.append(f"| {row['flops']:.2g} | {row['nmse']:.3g} / {nmse:.3g} | {nmse / nmae**2:.1f} | "
                         + " | ".join(f"{entry['shares'][name]:.0%}" for name in shares) + " |")
    ratio = [entry["scores"]["default"][1] / entry["scores"]["default"][0] ** 2 for entry in measured]
    lines.append(f"| all {len(measured)} | | {spread_text(ratio, '.1f')} | "
                 + " | ".join(spread_text([entry["shares"][name] for entry in measured], ".0%") for name in shares)
                 + " |")
    at = np.asarray(cfg["at"], dtype=float)
    law = published_law(key)
    assert law is not None
    lines += ["", f"**The nMSE envelope over the published law** (envelope of the {len(measured)} models; "
              f"within {cfg['within']:g}x at every resource: the test set that closes the gap)", "",
              "| scored on | " + " | ".join(map(resource_text, at)) + " | nMSE / nMAE^2 at the last | "
              f"within {cfg['within']:g}x |", "|---|" + "---:|" * (len(at) + 2)]
    r = np.array([entry["row"]["flops"] for entry in measured])
    for name in measured[0]["scores"]:
        nmae = np.array([entry["scores"][name][0] for entry in measured])
        nmse = np.array([entry["scores"][name][1] for entry in measured])
        ratios = step_envelope_at(r, nmse, at) / law.law.predict(at)
        best = int(np.argmin(nmse))
        known = ratios[~np.isnan(ratios)]
        within = bool(len(known)) and bool(np.all(np.maximum(known, 1 / known) <= cfg["within"]))
        lines.append(f"| {name} | " + " | ".join(map(factor_text, ratios))
                     + f" | {nmse[best] / nmae[best]**2:.1f} | {'yes' if within else 'no'} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
