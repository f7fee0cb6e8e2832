"""Post-process a sweep in one go: merge the rows, fit every NSL, check that the models learned (per (system, arch),
the share of tasks no better than the mean predictor, flagged where too many do not), draw the figures, write the
self-contained ``<sweep_dir>/report.html`` (and its comparison with the published laws as Markdown,
``comparison.md``) and log it all to MLflow.

    python -m nsl_hpc.report sweep_dir=runs/demo
    python -m nsl_hpc.report sweep_dir=runs/demo mlflow.tracking_uri=http://mlflow.example:5000
    python -m nsl_hpc.report sweep_dir=runs/io metrics=[nmae,nmae_one_step_test]   # other scores (docs/science.md)

Safe to re-run while a sweep is still going: every output is replaced atomically and MLflow runs are
updated, not duplicated. A tracking server (http, https) must answer within ``mlflow.timeout_s`` before anything
is written. The steps also run alone: ``python -m nsl_hpc.merge``, ``python -m nsl_hpc.fit``.
"""

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.analysis.figures import draw_figures, figure_stem
from nsl_hpc.analysis.fitted import fit_and_record
from nsl_hpc.analysis.fitting import fit_note, fits_path, nsl_key
from nsl_hpc.analysis.learning import learning_lines
from nsl_hpc.analysis.nsl_settings import MlflowSettings, figure_settings, nsl_settings
from nsl_hpc.analysis.prediction import what_it_takes
from nsl_hpc.analysis.report import comparison_markdown, report_html, scores_note, what_it_takes_html
from nsl_hpc.config.schema import typed
from nsl_hpc.core.atomic import write_text
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, require_sweep
from nsl_hpc.sweep.merge import merge_sweep, results_path


def main(cfg: DictConfig) -> int:
    settings = nsl_settings(cfg.nsl)
    figure_options = figure_settings(cfg.figures, settings.resources)
    sweep_dir = require_sweep(cfg.sweep_dir)
    mlflow = typed(MlflowSettings, cfg.mlflow, "mlflow")
    if mlflow.enabled:  # MLflow's import (1.6 s) only where the sweep is logged
        from nsl_hpc.analysis import mlflow_runs

        mlflow_runs.require_server(mlflow)
    launch_config = read_launch_config(sweep_dir)
    launch = launch_settings(launch_config)
    summary = merge_sweep(sweep_dir, cfg.compact)
    print(f"merged {summary.merged:,} tasks into {results_path(sweep_dir)}\n{summary.describe()}")
    fitted = fit_and_record(sweep_dir, settings, cfg.metrics, cfg.workers, launch)
    results, rows, nsl = fitted.results, fitted.rows, fitted.nsl
    print(f"{sum(row['error'] is None for row in rows)} of {len(rows)} NSLs fitted -> {fits_path(sweep_dir)}")
    print("\n".join(learning_lines(fitted.learning)))
    figures = draw_figures(sweep_dir, results, rows, nsl, figure_options)
    wanted = nsl.predict.report
    entries = what_it_takes(results, rows, wanted.resource, wanted.metric,
                            lambda best: [factor * best for factor in wanted.factors], nsl)
    section = what_it_takes_html(entries, wanted, nsl.resources[wanted.resource].symbol)
    scores = scores_note(launch.study.name, (launch_config.get("metric") or {}).get("normalization"))
    report = sweep_dir / layout.REPORT
    write_text(report_html(sweep_dir, launch, summary, rows, figures, section, nsl, fitted.cards["core_hours"],
                           fitted.learning, scores), report)
    notes = " ".join(note for note in (scores, fit_note(nsl)) if note)
    write_text(comparison_markdown(rows, notes), sweep_dir / layout.COMPARISON)
    if mlflow.enabled:
        by_key = {nsl_key(row): figure_stem(sweep_dir, row).with_suffix(".png") for row in rows}
        artifacts = [results_path(sweep_dir), fits_path(sweep_dir), sweep_dir / layout.FITS_TEXT, report,
                     sweep_dir / layout.COMPARISON,
                     *(path for path in figures["overview"])]
        experiment, run = mlflow_runs.log_to_mlflow(sweep_dir, mlflow, launch, summary, rows,
                                                    {key: path for key, path in by_key.items() if path.exists()},
                                                    artifacts)
        uri = mlflow_runs.tracking_uri(sweep_dir, mlflow.tracking_uri)
        print(f"MLflow: run {run} in {uri}; browse with `mlflow ui --backend-store-uri {uri}` at "
              f"#/experiments/{experiment}/runs (MLflow 3 opens on its GenAI overview)")
    print(f"report: {report.resolve()}")
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="report")
