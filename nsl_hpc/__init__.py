"""nsl_hpc: neural-scaling-law studies for learning-based system identification on SLURM clusters."""

__version__ = "0.2.0"
