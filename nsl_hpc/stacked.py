"""K state-space models of one architecture and depth as one set of stacked tensors: the fast training path.

Every architecture of the input-state study is a few tanh MLPs of one depth ("heads") on the same input,
plus a small assembly (nsl_hpc.models). Here the heads of one width, of all K models, are one batched MLP
(a "chain"): layer l is a (K, M, in_l, out_l) weight, so a forward pass costs depth + 2 batched matmuls per
chain however many models and heads there are (a per-model, per-head loop costs M K times as many small
operations, and at these sizes the cost of an operation is its overhead, not its arithmetic). Heads (and
models) narrower or with fewer inputs or outputs than the widest of their chain are zero-padded; padded
units compute exactly zero, and ``parameter_gradient`` masks their entries' gradients to exactly zero, so a padded
model computes and learns what it does alone. The port-Hamiltonian grad H is back-propagated through the
H head explicitly (first-order operations), not by a double backward.

All parameters of a model are one row of ``theta`` (K, P); the layers are leaf views into it, so the
optimizer step and the clipping norm are a handful of operations on (K, P) tensors.
"""

import itertools
from dataclasses import dataclass

import torch
from torch import nn

from nsl_hpc.models.input_affine import InputAffine
from nsl_hpc.models.unstructured import Unstructured

# Heads of different widths get chains of their own when K n_h (n_h of the widest) reaches this: measured
# (unstructured, K = 16) a second chain costs 10 % at n_h 8 and saves 10-15 % at n_h 16.
SPLIT_WIDTH = 256


@dataclass(frozen=True)
class Head:
    """One MLP of an architecture: its module name, whether it reads v as well as z, and its sizes."""

    name: str
    reads_input: bool
    in_dim: int
    out_dim: int
    width: int


def heads_of(model: nn.Module) -> list[Head]:
    """The MLP heads of an input-state model, in its module order."""
    heads = []
    for name, module in model.named_children():
        linears = [layer for layer in module if isinstance(layer, nn.Linear)]
        heads.append(Head(name, linears[0].in_features > model_state_dim(model), linears[0].in_features,
                          linears[-1].out_features, linears[0].out_features))
    return heads


def model_depth(model: nn.Module) -> int:
    """n_d: the hidden-to-hidden layers of each head."""
    return sum(isinstance(layer, nn.Linear) for layer in next(model.children())) - 2


def model_state_dim(model: nn.Module) -> int:
    return model.f[-1].out_features if isinstance(model, Unstructured) else model.n


def triangle_map(n: int, offset: int, antisymmetric: bool, dtype: torch.dtype) -> torch.Tensor:
    """(entries, n * n): maps the entries of a triangle (above the diagonal for offset 1, on and below it
    for offset 0, in triu/tril index order) to the flattened n x n matrix U - U^T (antisymmetric) or L."""
    rows, cols = torch.triu_indices(n, n, offset) if offset else torch.tril_indices(n, n)
    mapping = torch.zeros(len(rows), n * n, dtype=dtype)
    mapping[torch.arange(len(rows)), rows * n + cols] = 1.0
    if antisymmetric:
        mapping[torch.arange(len(rows)), cols * n + rows] = -1.0
    return mapping


@dataclass(frozen=True)
class Chain:
    """Heads of one width, computed as one batched MLP: ``heads`` are head indices; layer l of the chain is
    a (K, len(heads), in_l, out_l) weight."""

    heads: tuple[int, ...]
    shapes: tuple[tuple[int, int], ...]  # (in, out) of each layer


class StackedModels:
    """K models of one architecture and depth; ``theta`` (K, P) holds every parameter, zero-padded."""

    def __init__(self, models: list[nn.Module], dtype: torch.dtype):
        first = models[0]
        self.kind = type(first)
        self.heads = heads_of(first)
        self.n = model_state_dim(first)
        self.m = self.heads[-1].out_dim if isinstance(first, Unstructured) else first.m
        self.depth = model_depth(first)
        if any(type(model) is not self.kind or model_depth(model) != self.depth for model in models):
            raise ValueError(f"models stacked together need one architecture and depth ({self.kind.__name__}, "
                             f"n_d {self.depth}); widths may differ")
        self.chains = self.chains_of([heads_of(model) for model in models])
        self.use_theta(torch.zeros(len(models), sum(self.chain_size(chain) for chain in self.chains), dtype=dtype))
        self.scale = self.storage_scale(dtype)
        mask = torch.zeros_like(self.theta)
        for k, model in enumerate(models):
            self.load(k, model, mask)
        self.gradient_scale = self.scale * mask  # (K, P): 0 on padding
        n = self.n
        self.skew = triangle_map(n, offset=1, antisymmetric=True, dtype=dtype)  # entries -> J, flattened
        self.lower = triangle_map(n, offset=0, antisymmetric=False, dtype=dtype) * n ** -0.25  # L L^T = R

    def chains_of(self, model_heads: list[list[Head]]) -> list[Chain]:
        """One chain of all heads, padded to the widest head of any model; or, when K times that width is at
        least ``SPLIT_WIDTH``, a chain per head width of the first model (the unstructured f is twice as wide
        as g: padding g costs more arithmetic than a second chain costs overhead only for large K n_h)."""
        widest = max(head.width for heads in model_heads for head in heads)
        by_width: dict[int, list[int]] = {}
        for h, head in enumerate(model_heads[0]):
            by_width.setdefault(head.width if len(model_heads) * widest >= SPLIT_WIDTH else widest, []).append(h)
        chains = []
        for heads in by_width.values():
            in_dim = max(model_heads[0][h].in_dim for h in heads)
            out_dim = max(model_heads[0][h].out_dim for h in heads)
            width = max(one[h].width for one in model_heads for h in heads)
            dims = [in_dim, *[width] * (self.depth + 1), out_dim]
            chains.append(Chain(tuple(heads), tuple(itertools.pairwise(dims))))
        return chains

    def use_theta(self, theta: torch.Tensor) -> None:
        """Hold the parameters in ``theta`` (K, P); ``parameters`` are its layers' trainable leaf views."""
        self.theta = theta
        self.parameters = [tensor.requires_grad_(True) for layers in self.layers(theta)
                           for layer in layers for tensor in layer]

    def keep(self, rows: torch.Tensor) -> None:
        """Keep only the models of ``rows`` (K',): ``theta`` becomes a new (K', P) tensor."""
        self.use_theta(self.theta.detach()[rows])
        self.gradient_scale = self.gradient_scale[rows]

    def storage_scale(self, dtype: torch.dtype) -> torch.Tensor:
        """(1, P): ``theta`` holds each parameter times this factor, which puts the tanh-as-sigmoid factors
        into storage (see ``heads_forward``): weight and bias of a first layer 2, of a hidden layer 4 and 2,
        of a last layer 2 and 1."""
        scale = torch.ones(1, self.theta.shape[1], dtype=dtype)
        for chain, layers in zip(self.chains, self.layers(scale), strict=True):
            for index, (weight, bias) in enumerate(layers):
                last, hidden = index == len(chain.shapes) - 1, 0 < index < len(chain.shapes) - 1
                weight.fill_(4.0 if hidden else 2.0)
                bias.fill_(1.0 if last else 2.0)
        return scale

    def parameter_gradient(self, loss: torch.Tensor) -> torch.Tensor:
        """d loss / d parameters (K, P), as the modules' parameters (not their stored multiples), exactly 0 on
        padding entries."""
        grads = torch.autograd.grad(loss, self.parameters)
        return torch.cat([grad.reshape(self.count, -1) for grad in grads], dim=1).mul_(self.gradient_scale)

    @staticmethod
    def chain_size(chain: Chain) -> int:
        return sum(len(chain.heads) * (i * o + o) for i, o in chain.shapes)

    @property
    def count(self) -> int:
        return self.theta.shape[0]

    def layers(self, theta: torch.Tensor) -> list[list[tuple[torch.Tensor, torch.Tensor]]]:
        """Per chain, views (W (K, M_c, in, out), b (K, M_c, 1, out)) of each layer in ``theta`` (K, P)."""
        chains, offset = [], 0
        for chain in self.chains:
            views, heads = [], len(chain.heads)
            for i, o in chain.shapes:
                weight = theta[:, offset:offset + heads * i * o].view(-1, heads, i, o)
                offset += heads * i * o
                bias = theta[:, offset:offset + heads * o].view(-1, heads, 1, o)
                offset += heads * o
                views.append((weight, bias))
            chains.append(views)
        return chains

    def chain_parameters(self) -> list[list[tuple[torch.Tensor, torch.Tensor]]]:
        """The trainable leaf views of ``layers(theta)``."""
        pairs = iter(zip(self.parameters[::2], self.parameters[1::2], strict=True))
        return [[next(pairs) for _ in chain.shapes] for chain in self.chains]

    def load(self, k: int, model: nn.Module, mask: torch.Tensor) -> None:
        """Copy the parameters of ``model`` (times ``scale``) into row k; set its entries of ``mask`` (K, P) to 1."""
        with torch.no_grad():
            for chain, layers, mask_layers in zip(self.chains, self.chain_parameters(), self.layers(mask), strict=True):
                for position, h in enumerate(chain.heads):
                    linears = [layer for layer in getattr(model, self.heads[h].name) if isinstance(layer, nn.Linear)]
                    for (weight, bias), (weight_mask, bias_mask), linear in zip(layers, mask_layers, linears,
                                                                                 strict=True):
                        o, i = linear.weight.shape
                        weight[k, position, :i, :o] = linear.weight.T
                        bias[k, position, 0, :o] = linear.bias
                        weight_mask[k, position, :i, :o] = 1.0
                        bias_mask[k, position, 0, :o] = 1.0
            self.theta[k] *= self.scale[0]

    def heads_forward(self, z: torch.Tensor, v: torch.Tensor, theta: torch.Tensor | None = None
                      ) -> tuple[list[torch.Tensor], list]:
        """Output (K, B, out) of every head for z (K, B, n), v (K, B, m), with the trained parameters or the
        rows of ``theta`` (K, P); and per chain, its hidden layers' s (K, M_c, B, width) and its layers (for
        grad H).

        tanh(p) is computed as 2 s - 1 with s = sigmoid(2 p): torch's CPU sigmoid and its backward are several
        times faster than tanh's. The factor 2 of 2 p is in the stored weights (``storage_scale``) and the
        2 s - 1 is folded into the next layer, (2 s - 1) W + b = 2 s W + (b - 1^T W), so a layer is one matmul
        (its bias less half the stored weights' column sums) and one sigmoid. A head that reads fewer inputs
        than its chain has zero (padding) weights on the others.
        """
        outputs: list[torch.Tensor | None] = [None] * len(self.heads)
        internals = []
        zv = torch.cat([z, v], dim=-1) if any(chain.shapes[0][0] > self.n for chain in self.chains) else z
        chains = self.chain_parameters() if theta is None else self.layers(theta)
        for chain, layers in zip(self.chains, chains, strict=True):
            x = zv if chain.shapes[0][0] > self.n else z
            x = x.unsqueeze(1).expand(-1, len(chain.heads), -1, -1).flatten(0, 1)  # (K M_c, B, in)
            shape = (z.shape[0], len(chain.heads))
            sigmoids = []
            for index, (weight, bias) in enumerate(layers):
                weight, bias = weight.flatten(0, 1), bias.flatten(0, 1)
                if index:  # x is s of the previous layer: its tanh is 2 s - 1
                    bias = torch.sub(bias, weight.sum(dim=1, keepdim=True), alpha=0.5)
                if index == len(layers) - 1:
                    out = torch.baddbmm(bias, x, weight).view(*shape, x.shape[1], -1)
                    break
                x = torch.sigmoid(torch.baddbmm(bias, x, weight))
                sigmoids.append(x.view(*shape, *x.shape[1:]))
            for h, head_out in zip(chain.heads, out.unbind(1), strict=True):
                outputs[h] = head_out
            internals.append((sigmoids, layers))
        return outputs, internals

    def forward(self, z: torch.Tensor, v: torch.Tensor, theta: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (K, B, n) and y (K, B, m) of every model (or of the rows of ``theta`` (K, P)) for its own
        z (K, B, n), v (K, B, m)."""
        out, internals = self.heads_forward(z, v, theta)
        n, m = self.n, self.m
        if self.kind is Unstructured:
            return out[0][..., :n], out[1][..., :m]
        if self.kind is InputAffine:
            gain = out[1][..., :n * m].reshape(*z.shape[:2], n, m)
            return out[0][..., :n] + (gain @ v.unsqueeze(-1)).squeeze(-1), out[2][..., :m]
        grad = self.grad_hamiltonian(out[3], *internals[0])  # (K, B, n)
        rows = z.shape[0] * z.shape[1]
        interconnection = (out[0][..., :n * (n - 1) // 2].reshape(rows, -1) @ self.skew).view(rows, n, n)
        lower = (out[1][..., :n * (n + 1) // 2].reshape(rows, -1) @ self.lower).view(rows, n, n)
        dissipation = lower @ lower.transpose(1, 2)
        gain = out[2][..., :n * m].reshape(rows, n, m)
        grad = grad.reshape(rows, n, 1)
        dz = (interconnection - dissipation) @ grad + gain @ v.reshape(rows, m, 1)
        y = gain.transpose(1, 2) @ grad
        return dz.view(*z.shape), y.view(*v.shape)

    def grad_hamiltonian(self, h_out: torch.Tensor, sigmoids: list[torch.Tensor], layers: list) -> torch.Tensor:
        """grad_z of H = ||m(z)||^2 / 2 through the H head (index 3 of the one chain): (K, B, n). ``h_out``
        (K, B, out) = m(z); a hidden layer's tanh' = 1 - (2 s - 1)^2 = 4 s (1 - s). With the stored weights
        (2, 4, ..., 4, 2 times the modules') the factors 4 of the depth + 1 tanh' cancel."""
        g = h_out
        for (weight, _), sigmoid in zip(layers[:0:-1], sigmoids[::-1], strict=True):
            s = sigmoid[:, 3]
            g = (g @ weight[:, 3].transpose(1, 2)) * (s - s.square())
        return (g @ layers[0][0][:, 3].transpose(1, 2))[..., :self.n]
