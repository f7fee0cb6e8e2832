"""Writes data/tanks_train.csv and data/tanks_test.csv: the two-tank system driven by a random-phase multisine,
sampled every second, its level h2 measured with 1 mm noise. Run once: python make_data.py (the files ship)."""

from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from tanks import TwoTank

SAMPLE_TIME_S = 1.0


def record(seed: int, samples: int) -> np.ndarray:
    """(samples, 3): t, u, y of one experiment."""
    rng = np.random.default_rng(seed)
    tank = TwoTank(area=0.5, outlet1=0.01, outlet2=0.008, bias=0.03)
    t = np.arange(samples) * SAMPLE_TIME_S
    frequencies = np.arange(1, 60) / (samples * SAMPLE_TIME_S)  # up to 60 periods per record
    phases = rng.uniform(0, 2 * np.pi, len(frequencies))

    def u(time: float) -> float:
        return 0.0015 * np.sin(2 * np.pi * frequencies * time + phases).sum()

    solution = solve_ivp(lambda time, x: tank.derivative(x[None], np.array([[u(time)]]))[0], (0, t[-1]),
                         [0.4, 0.6], t_eval=t, rtol=1e-8, atol=1e-10)
    y = solution.y[1] + 0.001 * rng.standard_normal(samples)
    return np.stack([t, [u(time) for time in t], y], axis=-1)


if __name__ == "__main__":
    folder = Path(__file__).parent / "data"
    folder.mkdir(exist_ok=True)
    for name, seed, samples in (("tanks_train", 0, 4000), ("tanks_test", 1, 2000)):
        np.savetxt(folder / f"{name}.csv", record(seed, samples), delimiter=",", header="t,u,y", comments="",
                   fmt="%.6g")
