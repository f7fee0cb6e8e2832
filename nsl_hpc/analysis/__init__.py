"""From rows to findings: merge the rows, fit broken NSLs, draw the figures, log to MLflow, write the report.

    merge        rows -> results.parquet, with an account of tasks that have none
    broken_law   the broken power law and its fit to a lower envelope (fit_nsl)
    fitting      fit_nsl over every (system, arch, resource, metric) of a sweep
    bootstrap    intervals from refits on resampled outcomes
    published    the study's published laws beside ours
    prediction   the resource a law needs for a target error (python -m nsl_hpc.predict)
    figures      the figures of the fits
    mlflow_runs  one MLflow run per sweep, a child run per NSL
    report       report.html
"""
