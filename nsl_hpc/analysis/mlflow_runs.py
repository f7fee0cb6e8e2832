"""MLflow logging of a post-processed sweep: one parent run per sweep (its config as params, task counts
as metrics, merged table, fits, figures and report as artifacts) and one child run per NSL (its law as
params; M, the bootstrap intervals and the published law's M as metrics; its figure). Runs are found
again by tags, so post-processing twice updates them: a child whose law changed is replaced (MLflow params
are write-once), never duplicated.

The default store is ``sqlite:///<sweep_dir>/mlflow.db`` with artifacts in ``<sweep_dir>/mlartifacts``;
``mlflow.tracking_uri`` points at a team server instead. Only post-processing writes to MLflow: tasks
write Parquet rows, the source of truth.
"""

import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from mlflow.entities import Metric, Param, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from nsl_hpc.analysis.fitting import interval_columns, nsl_key
from nsl_hpc.analysis.nsl_settings import MlflowSettings
from nsl_hpc.config.mapping import flatten
from nsl_hpc.core.errors import RunError, one_line
from nsl_hpc.core.progress import progress
from nsl_hpc.core.seeding import stable_hash
from nsl_hpc.studies import study_named
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.merge import MergeSummary

SWEEP_TAG = "nsl_hpc.sweep.directory"  # the sweep directory, for people
SWEEP_ID_TAG = "nsl_hpc.sweep_id"  # a hash of it, for searches (a path may hold quotes; a hash holds none)
NSL_TAG = "nsl_hpc.analysis.broken_law"
PARENT_TAG = "mlflow.parentRunId"
LAW_COLUMNS = ("b", "alpha", "beta", "delta0")


def now_ms() -> int:
    """A metric's timestamp: MLflow shows the latest value of a step, so a re-run's values win."""
    return int(time.time() * 1000)


def tracking_uri(sweep_dir: Path, configured: str | None) -> str:
    return configured or f"sqlite:///{Path(sweep_dir).resolve() / layout.MLFLOW_DB}"


def require_server(settings: MlflowSettings) -> None:
    """Before any work: a RunError in one line unless the tracking server of an http(s) ``tracking_uri`` answers
    an MLflow request within ``timeout_s``; then bound MLflow's own requests (its defaults, 120 s and 7 retries
    with backoff, hang a report for many minutes on a server that is gone). Variables the user set
    (MLFLOW_HTTP_REQUEST_TIMEOUT, MLFLOW_HTTP_REQUEST_MAX_RETRIES) win after the first request."""
    uri = settings.tracking_uri
    if not settings.enabled or not uri or not uri.startswith(("http://", "https://")):
        return
    timeout = str(math.ceil(settings.timeout_s))
    probe = {"MLFLOW_HTTP_REQUEST_TIMEOUT": timeout, "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}
    after = {"MLFLOW_HTTP_REQUEST_TIMEOUT": timeout, "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2"}
    before = {name: os.environ.get(name) for name in probe}
    os.environ.update(probe)
    try:
        MlflowClient(uri).search_experiments(max_results=1)
    except Exception as error:  # requests' connection errors, MLflow's on an answer that is no MLflow's
        reason = one_line(error)[:160]
        raise RunError(f"no MLflow tracking server answers at {uri} (mlflow.timeout_s={settings.timeout_s:g}; "
                       f"{type(error).__name__}: {reason}); nothing was written: start it, fix "
                       "mlflow.tracking_uri, or set mlflow.enabled=false") from None
    finally:
        os.environ.update({name: before[name] or value for name, value in after.items()})


def experiment_id(client: MlflowClient, name: str, sweep_dir: Path, default_store: bool) -> str:
    experiment = client.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    location = (Path(sweep_dir).resolve() / layout.MLFLOW_ARTIFACTS).as_uri() if default_store else None
    return client.create_experiment(name, artifact_location=location)


def law_params(row: Mapping[str, Any]) -> dict[str, str]:
    """An NSL's law as MLflow params: b, alpha, beta, delta0, sigma_i, phi_i, delta_i for i <= b."""
    params = {name: str(row[name]) for name in LAW_COLUMNS}
    for i in range(1, row["b"] + 1):
        params.update({f"{name}_{i}": str(row[f"{name}_{i}"]) for name in ("sigma", "phi", "delta")})
    return params


def find_runs(client: MlflowClient, experiment: str, filter_string: str) -> list:
    return client.search_runs([experiment], filter_string=filter_string, max_results=10_000)


def sweep_run(client: MlflowClient, experiment: str, sweep_dir: Path, name: str, params: dict[str, str]) -> str:
    """The sweep's parent run (created with its params the first time)."""
    path = str(Path(sweep_dir).resolve())
    key = stable_hash(path)
    runs = find_runs(client, experiment, f"tags.`{SWEEP_ID_TAG}` = '{key}' and tags.`{NSL_TAG}` = 'sweep'")
    if runs:
        return runs[0].info.run_id
    run = client.create_run(experiment, run_name=name, tags={SWEEP_TAG: path, SWEEP_ID_TAG: key, NSL_TAG: "sweep"})
    items = sorted(params.items())
    for start in range(0, len(items), 100):  # log_batch takes at most 100 params
        client.log_batch(run.info.run_id, params=[Param(k, v[:6000]) for k, v in items[start:start + 100]])
    return run.info.run_id


def log_nsl_runs(client: MlflowClient, experiment: str, parent: str, rows: Sequence[Mapping[str, Any]],
                 figures: Mapping[str, Path]) -> None:
    """One child run per fitted NSL, reused while its law is unchanged, replaced otherwise."""
    children = find_runs(client, experiment, f"tags.`{PARENT_TAG}` = '{parent}'")
    existing = {run.data.tags[NSL_TAG]: run for run in children}
    for row in progress([row for row in rows if row["error"] is None], "MLflow runs", "NSL"):
        key = nsl_key(row)
        params = law_params(row)
        run = existing.pop(key, None)
        if run is not None and run.data.params != params:
            client.delete_run(run.info.run_id)
            run = None
        if run is None:
            run = client.create_run(experiment, run_name=key.replace("/", " "),
                                    tags={NSL_TAG: key, PARENT_TAG: parent})
            client.log_batch(run.info.run_id, params=[Param(k, v) for k, v in params.items()])
        run_id = run.info.run_id
        metrics = {"M": row["margin"], "outcomes": row["outcomes"], "backtest_M": row["backtest_margin"],
                   "paper_M": row.get("paper_margin"), "paper_M_on_ours": row.get("paper_margin_on_ours"),
                   **{name: row.get(name) for name in interval_columns(row["b"])}}
        metrics = {name: value for name, value in metrics.items() if value is not None}
        client.log_batch(run_id, metrics=[Metric(k, float(v), now_ms(), 0) for k, v in metrics.items()],
                         tags=[RunTag("formula", row["formula"])])
        if key in figures:
            client.log_artifact(run_id, str(figures[key]))
        client.set_terminated(run_id)
    for stale in existing.values():  # NSLs no longer fitted
        client.delete_run(stale.info.run_id)


def log_to_mlflow(sweep_dir: Path, settings: MlflowSettings, launch: LaunchSettings,
                  summary: MergeSummary, rows: Sequence[Mapping[str, Any]], figures: Mapping[str, Path],
                  artifacts: Sequence[Path]) -> tuple[str, str]:
    """Log (or update) the sweep's runs; returns the experiment's id and the parent run's. A RunError in one line
    when the store fails on the way (what is on disk stays: a re-run logs it)."""
    try:
        return logged(sweep_dir, settings, launch, summary, rows, figures, artifacts)
    except (MlflowException, OSError) as error:
        raise RunError(f"logging to MLflow at {tracking_uri(sweep_dir, settings.tracking_uri)} failed "
                       f"({type(error).__name__}: {one_line(error)[:160]}); the results, fits, figures "
                       "and report on disk are complete: run the report again to log them") from None


def logged(sweep_dir: Path, settings: MlflowSettings, launch: LaunchSettings,
           summary: MergeSummary, rows: Sequence[Mapping[str, Any]], figures: Mapping[str, Path],
           artifacts: Sequence[Path]) -> tuple[str, str]:
    """``log_to_mlflow``'s work."""
    client = MlflowClient(tracking_uri(sweep_dir, settings.tracking_uri))
    experiment = experiment_id(client, settings.experiment, sweep_dir, settings.tracking_uri is None)
    study = study_named(launch.study.name)
    keys = ("sweep", "sweep_seed", "study", *(key for key in study.shared_keys if key not in ("system", "arch")))
    params = flatten({key: launch.values[key] for key in keys})  # the sweep's config as it was written
    parent = sweep_run(client, experiment, sweep_dir, launch.sweep.name, params)
    counts = {name: value for name, value in asdict(summary).items() if isinstance(value, int)}
    metrics = {**counts, "dropped": summary.dropped, "dropped_fraction": summary.dropped / max(summary.tasks, 1),
               "nsl_fitted": sum(row["error"] is None for row in rows)}
    client.log_batch(parent, metrics=[Metric(k, float(v), now_ms(), 0) for k, v in metrics.items()])
    for path in artifacts:
        if path.is_dir():
            client.log_artifacts(parent, str(path), artifact_path=path.name)
        else:
            client.log_artifact(parent, str(path))
    log_nsl_runs(client, experiment, parent, rows, figures)
    client.set_terminated(parent)
    return experiment, parent
