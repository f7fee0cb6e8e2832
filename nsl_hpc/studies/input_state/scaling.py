"""The input-state models' view of a data set: standardised inputs and the targets they are trained on.

Models read standardised inputs, fitted on the training data (ddof 0, as scikit-learn's StandardScaler):
z = (x - mean_x) / std_x, v = (u - mean_u) / std_u. Their targets are dx/dt and y as they are (the study's,
``train.rescale_targets: false``), or rescaled (``true``, nsl_hpc before): dx/dt / std_x in a time unit in
which it is O(1), and y std_u divided by its RMS (a port-Hamiltonian model in these coordinates is one in x,
u, t as well: the diagonal std_x keeps J skew and R PSD, and the two scalar rescalings only scale J, R and H).
"""

from dataclasses import dataclass

import numpy as np
import torch

from nsl_hpc.studies.input_state.data import Dataset
from nsl_hpc.studies.training import nonzero


@dataclass(frozen=True)
class Scaling:
    """Input standardisation and target units fitted on training data; arrays are (n,) or (m,)."""

    x_mean: np.ndarray
    x_std: np.ndarray
    u_mean: np.ndarray
    u_std: np.ndarray
    derivative_unit: np.ndarray  # a model's dz/dt target is dx/dt / derivative_unit
    output_unit: np.ndarray  # and its y target y / output_unit

    @classmethod
    def fit(cls, data: Dataset, rescale_targets: bool) -> "Scaling":
        x_std, u_std = nonzero(data.x.std(axis=0)), nonzero(data.u.std(axis=0))
        if not rescale_targets:
            return cls(data.x.mean(axis=0), x_std, data.u.mean(axis=0), u_std, np.ones_like(x_std),
                       np.ones_like(u_std))
        rms = lambda a: float(nonzero(np.sqrt(np.mean(np.square(a)))))  # noqa: E731
        return cls(data.x.mean(axis=0), x_std, data.u.mean(axis=0), u_std, x_std * rms(data.dx / x_std),
                   rms(data.y * u_std) / u_std)

    def model_inputs(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n), v (N, m)."""
        return (torch.as_tensor((data.x - self.x_mean) / self.x_std, dtype=dtype),
                torch.as_tensor((data.u - self.u_mean) / self.u_std, dtype=dtype))

    def model_targets(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """The dz/dt (N, n) and y (N, m) a model is trained to output."""
        return (torch.as_tensor(data.dx / self.derivative_unit, dtype=dtype),
                torch.as_tensor(data.y / self.output_unit, dtype=dtype))
