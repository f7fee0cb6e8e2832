"""nsl_hpc: neural-scaling-law studies for learning-based system identification on SLURM clusters.

The commands are ``python -m nsl_hpc.<command>`` (launch, status, resubmit, clean, train, merge, fit, predict,
report, bench, place_data); the public fitting API is ``fit_nsl`` and ``backtest_nsl`` (``nsl_hpc.nsl``).
"""

from typing import Any

__version__ = "0.2.0"
__all__ = ["__version__", "backtest_nsl", "fit_nsl"]


def __getattr__(name: str) -> Any:
    """``nsl_hpc.fit_nsl`` and ``nsl_hpc.backtest_nsl``, loaded on first use (PEP 562): every command and job
    imports this package, and only fits need the fitting code (scipy.optimize and the law)."""
    if name in ("fit_nsl", "backtest_nsl"):
        from nsl_hpc import nsl

        return getattr(nsl, name)
    raise AttributeError(f"module 'nsl_hpc' has no attribute {name!r}")
