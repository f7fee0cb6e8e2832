"""K state-space models of one architecture and shape as one set of stacked tensors: the fast training path.

Every architecture of the input-state study is a few tanh MLPs of one depth ("heads") on the same input,
plus a small assembly (nsl_hpc.models). Here the heads of all K models are one batched MLP: layer l is a
(K, M, in_l, out_l) weight, so a forward pass costs depth + 2 batched matmuls however many models and heads
there are (a per-model, per-head loop costs M K times as many small operations, and at these sizes the
cost of an operation is its overhead, not its arithmetic). Heads (and models) narrower or with fewer inputs
or outputs than the widest are zero-padded; padded units compute exactly zero, and ``trainable`` masks their
entries' gradients to exactly zero, so a padded model computes and learns what it does alone. The port-Hamiltonian
grad H is back-propagated through the H head explicitly (first-order operations), not by a double backward.

All parameters of a model are one row of ``theta`` (K, P); the layers are leaf views into it, so the
optimizer step and the clipping norm are a handful of operations on (K, P) tensors.
"""

import itertools
from dataclasses import dataclass

import torch
from torch import nn

from nsl_hpc.models.input_affine import InputAffine
from nsl_hpc.models.unstructured import Unstructured


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


class StackedModels:
    """K models of one architecture and shape; ``theta`` (K, P) holds every parameter, zero-padded."""

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
        self.in_dim = max(head.in_dim for head in self.heads)
        self.width = max(head.width for model in models for head in heads_of(model))
        self.out_dim = max(head.out_dim for head in self.heads)
        dims = [self.in_dim, *[self.width] * (self.depth + 1), self.out_dim]
        self.shapes = list(itertools.pairwise(dims))  # (in, out) of each layer
        size = sum(len(self.heads) * (i * o + o) for i, o in self.shapes)
        self.theta = torch.zeros(len(models), size, dtype=dtype)
        self.parameters = [tensor.requires_grad_(True) for layer in self.layers(self.theta) for tensor in layer]
        mask = torch.zeros_like(self.theta)
        for k, model in enumerate(models):
            self.load(k, model, mask)
        self.trainable = None if bool(mask.all()) else mask  # (K, P): 1 on a model's own parameters
        n = self.n
        self.skew = triangle_map(n, offset=1, antisymmetric=True, dtype=dtype)  # entries -> J, flattened
        self.lower = triangle_map(n, offset=0, antisymmetric=False, dtype=dtype) * n ** -0.25  # L L^T = R
        self.input_mask = torch.tensor([[1.0] * self.n + [float(h.reads_input)] * (self.in_dim - self.n)
                                        for h in self.heads], dtype=dtype)[:, None, :]  # (M, 1, in)

    @property
    def count(self) -> int:
        return self.theta.shape[0]

    def layers(self, theta: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Views (W (K, M, in, out), b (K, M, 1, out)) of each layer in ``theta`` (K, P)."""
        views, offset, heads = [], 0, len(self.heads)
        for i, o in self.shapes:
            weight = theta[:, offset:offset + heads * i * o].view(-1, heads, i, o)
            offset += heads * i * o
            bias = theta[:, offset:offset + heads * o].view(-1, heads, 1, o)
            offset += heads * o
            views.append((weight, bias))
        return views

    def load(self, k: int, model: nn.Module, mask: torch.Tensor) -> None:
        """Copy the parameters of ``model`` into row k, and set its entries of ``mask`` (K, P) to 1."""
        with torch.no_grad():
            layers = list(zip(self.parameters[::2], self.parameters[1::2], strict=True))
            mask_layers = self.layers(mask)
            for h, head in enumerate(self.heads):
                linears = [layer for layer in getattr(model, head.name) if isinstance(layer, nn.Linear)]
                for (weight, bias), (weight_mask, bias_mask), linear in zip(layers, mask_layers, linears, strict=True):
                    o, i = linear.weight.shape
                    weight[k, h, :i, :o] = linear.weight.T
                    bias[k, h, 0, :o] = linear.bias
                    weight_mask[k, h, :i, :o] = 1.0
                    bias_mask[k, h, 0, :o] = 1.0

    def heads_forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor], list]:
        """Outputs (K, M, B, out) of every head for z (K, B, n), v (K, B, m); also the hidden layers' s (for
        grad H) and the layers.

        tanh(p) is computed as 2 s - 1 with s = sigmoid(2 p): torch's CPU sigmoid and its backward are several
        times faster than tanh's. The factor 2 of 2 p goes into the weights and the 2 s - 1 is folded into
        the next layer, (2 s - 1) W + b = 2 s W + (b - 1^T W), so a hidden layer is one matmul and one sigmoid.
        """
        x = torch.cat([z, v], dim=-1) if self.in_dim > self.n else z
        x = (x.unsqueeze(1) * self.input_mask).flatten(0, 1)  # (K M, B, in)
        layers = list(zip(self.parameters[::2], self.parameters[1::2], strict=True))
        shape = (self.count, len(self.heads))
        sigmoids = []
        for index, (weight, bias) in enumerate(layers):
            weight, bias = weight.flatten(0, 1), bias.flatten(0, 1)
            if index:  # x is s of the previous layer: its tanh is 2 s - 1
                bias, scale = bias - weight.sum(dim=1, keepdim=True), 2.0
            else:
                scale = 1.0
            if index == len(layers) - 1:
                out = torch.baddbmm(bias, x, weight * scale)
                return out.view(*shape, *out.shape[1:]), sigmoids, layers
            # the factors scale the small weight and bias tensors, not the (K M, B, width) activations
            x = torch.sigmoid(torch.baddbmm(bias * 2.0, x, weight * (2.0 * scale)))
            sigmoids.append(x.view(*shape, *x.shape[1:]))
        raise AssertionError("a model has at least two layers")

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (K, B, n) and y (K, B, m) of every model for its own z (K, B, n), v (K, B, m)."""
        out, sigmoids, layers = self.heads_forward(z, v)
        n, m = self.n, self.m
        if self.kind is Unstructured:
            return out[:, 0, :, :n], out[:, 1, :, :m]
        if self.kind is InputAffine:
            gain = out[:, 1, :, :n * m].reshape(*z.shape[:2], n, m)
            return out[:, 0, :, :n] + (gain @ v.unsqueeze(-1)).squeeze(-1), out[:, 2, :, :m]
        grad = self.grad_hamiltonian(out[:, 3], sigmoids, layers)  # (K, B, n)
        rows = z.shape[0] * z.shape[1]
        interconnection = (out[:, 0, :, :n * (n - 1) // 2].reshape(rows, -1) @ self.skew).view(rows, n, n)
        lower = (out[:, 1, :, :n * (n + 1) // 2].reshape(rows, -1) @ self.lower).view(rows, n, n)
        dissipation = lower @ lower.transpose(1, 2)
        gain = out[:, 2, :, :n * m].reshape(rows, n, m)
        grad = grad.reshape(rows, n, 1)
        dz = (interconnection - dissipation) @ grad + gain @ v.reshape(rows, m, 1)
        y = gain.transpose(1, 2) @ grad
        return dz.view(*z.shape), y.view(*v.shape)

    def grad_hamiltonian(self, h_out: torch.Tensor, sigmoids: list[torch.Tensor], layers: list) -> torch.Tensor:
        """grad_z of H = ||m(z)||^2 / 2 through the H head (index 3): (K, B, n). ``h_out`` (K, B, out) = m(z);
        a hidden layer's tanh' = 1 - (2 s - 1)^2 = 4 s (1 - s)."""
        g = h_out
        for (weight, _), sigmoid in zip(layers[:0:-1], sigmoids[::-1], strict=True):
            s = sigmoid[:, 3]
            g = (g @ weight[:, 3].transpose(1, 2)) * (4 * s * (1 - s))
        return (g @ layers[0][0][:, 3].transpose(1, 2))[..., :self.n]
