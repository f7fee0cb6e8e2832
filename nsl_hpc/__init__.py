"""nsl_hpc: neural-scaling-law studies for learning-based system identification on SLURM clusters.

The commands are ``python -m nsl_hpc.<command>`` (launch, status, resubmit, clean, train, merge, fit, predict,
report, bench, place_data); the public fitting API is ``fit_nsl`` and ``backtest_nsl`` (``nsl_hpc.nsl``).
"""

__version__ = "0.2.0"

from nsl_hpc.nsl import backtest_nsl, fit_nsl  # after __version__, which the modules it loads read

__all__ = ["__version__", "backtest_nsl", "fit_nsl"]
