"""Unstructured state-space model (3a): dx/dt = f(x, u), y = g(x).

``form: joint`` (the study's, the authors' Baseline): one MLP of width round(width_factor n_h) from (x, u) to
(dx/dt, y), so y may depend on u too. ``form: split``: f of width round(width_factor n_h) on (x, u) and g of
width n_h on x alone, as (3a) is written.
"""

import torch

from nsl_hpc.models.blocks import Head
from nsl_hpc.models.state_space import Outputs, StateSpaceArchitecture
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, Layout


class Unstructured(StateSpaceArchitecture):
    def __init__(self, state_dim: int, input_dim: int, width: int, form: str, width_factor: float):
        super().__init__(state_dim, input_dim, width)
        self.form, self.f_width = form, self.scaled_width(width_factor)

    def heads(self) -> list[Head]:
        if self.form == "joint":
            return [Head("f", True, self.n + self.m, self.f_width)]
        return [Head("f", True, self.n, self.f_width), Head("g", False, self.m, self.width)]

    def assemble(self, outputs: Outputs, v: torch.Tensor, grad_energy: torch.Tensor | None,
                 layout: Layout = BATCH_MAJOR) -> tuple[torch.Tensor, torch.Tensor]:
        if self.form == "joint":
            return layout.take(outputs["f"], 0, self.n), layout.take(outputs["f"], self.n, self.n + self.m)
        return outputs["f"], outputs["g"]
