"""Input-affine state-space model (3b): dx/dt = h(x) + j(x) u, y = k(x), with j(x) an n x m matrix.

The study's form is the paper's: three MLPs of width n_h. The authors' code adds a feedthrough D(x) u to y
(``feedthrough: true``, a fourth MLP of m x m outputs) and doubles the width (``width_factor: 2``).
"""

import torch

from nsl_hpc.models.blocks import Head
from nsl_hpc.models.state_space import Outputs, StateSpaceArchitecture
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, Layout


class InputAffine(StateSpaceArchitecture):
    def __init__(self, state_dim: int, input_dim: int, width: int, width_factor: float, feedthrough: bool):
        super().__init__(state_dim, input_dim, width)
        self.head_width, self.feedthrough = self.scaled_width(width_factor), feedthrough

    def heads(self) -> list[Head]:
        n, m, width = self.n, self.m, self.head_width
        heads = [Head("h", False, n, width), Head("j", False, n * m, width), Head("k", False, m, width)]
        return [*heads, Head("d", False, m * m, width)] if self.feedthrough else heads

    def assemble(self, outputs: Outputs, v: torch.Tensor, grad_energy: torch.Tensor | None,
                 layout: Layout = BATCH_MAJOR) -> tuple[torch.Tensor, torch.Tensor]:
        n, m, u = self.n, self.m, layout.column(v)
        dz = outputs["h"] + layout.vector(layout.matmul(layout.matrix(outputs["j"], n, m), u))
        y = outputs["k"]
        if self.feedthrough:
            y = y + layout.vector(layout.matmul(layout.matrix(outputs["d"], m, m), u))
        return dz, y
