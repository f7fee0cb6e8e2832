"""From rows to findings (the merged rows of nsl_hpc.sweep.merge): fit broken NSLs, say how sure they are and what
they predict, draw the figures, log to MLflow, write the report. docs/layout.md lists each module."""
