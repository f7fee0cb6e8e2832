"""Models of a user's own ``torch.nn.Module`` (an ``arch`` whose ``_target_`` builds one) in the stack's interface,
so the lockstep training, its checkpoints and the scoring run them as they run ``StackedModels``: their parameters
are rows of ``theta`` (K, P), and each model's forward pass is its module's, called with its row
(``torch.func.functional_call``). Such models are not batched into one computation: the planner gives each its own
group (a ``stackable`` of False in the manifest), so K is 1 in a sweep."""

import torch
from torch import nn
from torch.func import functional_call


class ModuleStack:
    """K modules of one class and shape; ``theta`` (K, P) holds their parameters, in ``named_parameters`` order."""

    def __init__(self, models: list[nn.Module], dtype: torch.dtype, state_dim: int, input_dim: int):
        self.module, self.n, self.m = models[0], state_dim, input_dim
        self.shapes = [(name, tuple(p.shape)) for name, p in self.module.named_parameters()]
        if any([(name, tuple(p.shape)) for name, p in model.named_parameters()] != self.shapes for model in models):
            raise ValueError(f"models of {type(self.module).__name__} stacked together need one shape")
        rows = [torch.cat([p.detach().reshape(-1) for p in model.parameters()]) for model in models]
        self.use_theta(torch.stack(rows).to(dtype))
        self.gradient_mask = torch.ones_like(self.theta)  # no padding

    def use_theta(self, theta: torch.Tensor) -> None:
        """Hold the parameters in ``theta`` (K, P); ``leaf`` shares its storage and carries the gradient."""
        self.theta = theta
        self.leaf = theta.detach().requires_grad_(True)

    def keep(self, rows: torch.Tensor) -> None:
        """Keep only the models of ``rows`` (K',)."""
        self.use_theta(self.theta.detach()[rows])
        self.gradient_mask = self.gradient_mask[rows]

    @property
    def count(self) -> int:
        return self.theta.shape[0]

    def parameters_of(self, row: torch.Tensor) -> dict[str, torch.Tensor]:
        """One model's parameters by name, views of its row (P,)."""
        named, offset = {}, 0
        for name, shape in self.shapes:
            size = int(torch.Size(shape).numel())
            named[name] = row[offset:offset + size].view(shape)
            offset += size
        return named

    def forward(self, zv: torch.Tensor, theta: torch.Tensor | None = None,
                models: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (K, n, B) and y (K, m, B) for zv (K, n + m, B) of the models training (``leaf``), or of
        parameters ``theta`` (K, P) (``models``: which; the call gives each its row)."""
        rows = self.leaf if theta is None else theta
        outputs = [functional_call(self.module, self.parameters_of(rows[k]), (zv[k, :self.n].T, zv[k, self.n:].T))
                   for k in range(len(rows))]
        return (torch.stack([dz.T for dz, _ in outputs]), torch.stack([y.T for _, y in outputs]))

    def parameter_gradient(self, loss: torch.Tensor) -> torch.Tensor:
        """d loss / d parameters (K, P)."""
        (grad,) = torch.autograd.grad(loss, self.leaf, materialize_grads=True)
        return grad
