"""Wiener-Hammerstein chain, the simulated stand-in of the WH benchmark: LTI filter, static saturating
nonlinearity, LTI filter (like the benchmark's two third-order filters around a diode-resistor circuit)."""

import numpy as np


def simulate_wiener_hammerstein(u: np.ndarray, fs_hz: float, order: int, first_cutoff_hz: float,
                                first_ripple_db: float, second_cutoff_hz: float, second_attenuation_db: float,
                                saturation: float) -> np.ndarray:
    """Output y (N,) for the input u (N,) from rest: Chebyshev type I lowpass, then
    saturation * tanh(x / saturation), then Chebyshev type II lowpass."""
    from scipy import signal  # ~1 s to import: only the tasks that simulate pay it, not every command

    first = signal.cheby1(order, first_ripple_db, first_cutoff_hz, fs=fs_hz)
    second = signal.cheby2(order, second_attenuation_db, second_cutoff_hz, fs=fs_hz)
    inner = signal.lfilter(*first, u)
    return signal.lfilter(*second, saturation * np.tanh(inner / saturation))
