"""K input-state models of one architecture and depth as one set of stacked tensors: the fast training path.

Every architecture is a few MLPs of one depth ("heads", declared by the architecture: ``nsl_hpc.models``)
plus an assembly of their outputs. Here the heads of one width, of all K models, are one batched MLP (a
"chain"): hidden layer l is a (K, M, in_l, width) weight (with its LayerNorm's (K, M, 1, width) scale and
shift), so a forward pass costs about 3 n_d + 1 batched operations per chain however many models and heads
there are (a per-model, per-head loop costs M K times as many small operations, and at these sizes the cost
of an operation is its overhead, not its arithmetic). The outputs then go through the architecture's own
``assemble``, the code the modules run.

A chain computes feature-major: its activations are (K M, width, B), so a LayerNorm reduces over ``width`` rows
of B contiguous samples rather than over rows of 2-16 units (benchmarks/feature_major.py, one chain at K = 32:
1.7-2.5x faster eager and 2.7-3x compiled at n_h 2-8, about even at n_h 16 x 4 and wider). Inputs and outputs
are feature-major too, (K, features, B), and the architecture assembles its outputs feature-major
(``models.layout``): the per-sample matrix products of the port-Hamiltonian and input-affine models are then
elementwise operations over rows of B samples, not batched matmuls of K B tiny matrices.

Heads (and models) narrower or with fewer inputs or outputs than the widest of their chain are zero-padded;
LayerNorm averages over each model's own units only, padded units compute exactly zero, and
``parameter_gradient`` masks their entries' gradients to exactly zero, so a padded model computes and learns
what it does alone. The port-Hamiltonian grad H is back-propagated through the H head explicitly (first-order
operations that autograd differentiates once more), not by a double backward through every head.

All parameters of a model are one row of ``theta`` (K, P); the layers are leaf views into it, so the optimizer
step and the clipping norm are a handful of operations on (K, P) tensors.
"""

from dataclasses import dataclass
from typing import cast

import torch
from torch.nn import functional

from nsl_hpc.models.blocks import Head, masked_layer_norm
from nsl_hpc.models.state_space import StateSpaceModel
from nsl_hpc.models.tensor_layout import FEATURE_MAJOR

# Heads of different widths get chains of their own when K n_h (n_h of the widest) reaches this: measured
# (unstructured, split form, K = 16) a second chain costs 10 % at n_h 8 and saves 10-15 % at n_h 16.
SPLIT_WIDTH = 256

Layer = tuple[torch.Tensor, ...]  # weight (K, M, in, out), bias (K, M, 1, out)[, LayerNorm scale, shift (K, M, 1, out)]


def shape_of(model: StateSpaceModel) -> tuple:
    """What models stacked together share: architecture, depth, block and heads (all but their widths)."""
    heads = tuple((head.name, head.reads_input, head.out_dim) for head in model.architecture.heads())
    return type(model.architecture), model.depth, model.block, heads


@dataclass(frozen=True)
class Units:
    """Each model's own hidden units in a chain: ``mask`` (K, M_c, width, 1) 1 on them, ``inverse``
    (K, M_c, 1, 1) 1 / their number."""

    mask: torch.Tensor
    inverse: torch.Tensor

    @classmethod
    def of(cls, chain: "Chain", model_heads: list[list[Head]], dtype: torch.dtype) -> "Units":
        units = torch.tensor([[heads[h].width for h in chain.heads] for heads in model_heads], dtype=dtype)
        return cls((torch.arange(chain.width) < units[..., None]).to(dtype)[..., None], (1.0 / units)[..., None, None])

    def rows(self, models: torch.Tensor) -> "Units":
        return Units(self.mask[models], self.inverse[models])


@dataclass(frozen=True)
class Chain:
    """Heads of one width computed as one batched MLP: ``heads`` are head indices, ``in_dim`` the columns it
    reads (n, or n + m when a head reads v), ``width`` its hidden width, ``out_dim`` its widest output."""

    heads: tuple[int, ...]
    in_dim: int
    width: int
    out_dim: int


def feature_major(tensor: torch.Tensor) -> torch.Tensor:
    """A layer's (K, M_c, rows, columns) tensor as (K M_c, columns, rows): a weight as it multiplies a
    feature-major (K M_c, in, B) activation, a bias or LayerNorm affine as a (K M_c, out, 1) column."""
    return tensor.flatten(0, 1).transpose(1, 2)


class StackedModels:
    """K models of one architecture, depth and block; ``theta`` (K, P) holds every parameter, zero-padded."""

    def __init__(self, models: list[StateSpaceModel], dtype: torch.dtype):
        first = models[0]
        self.architecture, self.depth, self.block = first.architecture, first.depth, first.block
        self.heads = self.architecture.heads()
        self.n, self.m = self.architecture.n, self.architecture.m
        self.layer_norm = self.block == "layernorm_silu"
        if any(shape_of(model) != shape_of(first) for model in models):
            raise ValueError(f"models stacked together need one architecture, depth and block ("
                             f"{type(self.architecture).__name__}, n_d {self.depth}, {self.block}); widths may differ")
        model_heads = [model.architecture.heads() for model in models]
        self.chains = self.chains_of(model_heads)
        self.use_theta(torch.zeros(len(models), sum(self.chain_size(chain) for chain in self.chains), dtype=dtype))
        mask = torch.zeros_like(self.theta)
        for k, model in enumerate(models):
            self.load(k, model, mask)
        self.gradient_mask = mask  # (K, P): 0 on padding
        self.masked = bool((mask == 0).any())  # some entry is padding
        self.model_units = [Units.of(chain, model_heads, dtype) for chain in self.chains]  # of every model given
        self.padded = [bool((units.mask == 0).any()) for units in self.model_units]
        self.models = torch.arange(len(models))  # the models of the rows of theta
        self.units = self.model_units

    def chains_of(self, model_heads: list[list[Head]]) -> list[Chain]:
        """One chain of all heads, padded to the widest head of any model; or, when K times that width is at
        least ``SPLIT_WIDTH``, a chain per head width of the first model (padding a narrow head costs more
        arithmetic than a second chain costs overhead only for large K n_h)."""
        widest = max(head.width for heads in model_heads for head in heads)
        by_width: dict[int, list[int]] = {}
        for h, head in enumerate(model_heads[0]):
            by_width.setdefault(head.width if len(model_heads) * widest >= SPLIT_WIDTH else widest, []).append(h)
        return [Chain(tuple(heads), max(self.n + self.m if self.heads[h].reads_input else self.n for h in heads),
                      max(one[h].width for one in model_heads for h in heads),
                      max(self.heads[h].out_dim for h in heads))
                for heads in by_width.values()]

    def tensor_shapes(self, chain: Chain) -> list[list[tuple[int, int]]]:
        """(rows, columns) of each tensor of each layer of ``chain``, per head."""
        hidden = [[(fan_in, chain.width), (1, chain.width)] + ([(1, chain.width)] * 2 if self.layer_norm else [])
                  for fan_in in [chain.in_dim] + [chain.width] * (self.depth - 1)]
        return [*hidden, [(chain.width, chain.out_dim), (1, chain.out_dim)]]

    def chain_size(self, chain: Chain) -> int:
        return sum(len(chain.heads) * rows * columns for layer in self.tensor_shapes(chain) for rows, columns in layer)

    def use_theta(self, theta: torch.Tensor) -> None:
        """Hold the parameters in ``theta`` (K, P); ``parameters`` are its layers' trainable leaf views."""
        self.theta = theta
        self.parameters = [tensor.requires_grad_(True) for layers in self.layers(theta) for layer in layers
                           for tensor in layer]

    def keep(self, rows: torch.Tensor) -> None:
        """Keep only the models of ``rows`` (K',): ``theta`` becomes a new (K', P) tensor."""
        self.use_theta(self.theta.detach()[rows])
        self.gradient_mask = self.gradient_mask[rows]
        self.masked = bool((self.gradient_mask == 0).any())
        self.models = self.models[rows]
        self.units = [units.rows(self.models) for units in self.model_units]

    def parameter_gradient(self, loss: torch.Tensor) -> torch.Tensor:
        """d loss / d parameters (K, P), exactly 0 on padding entries."""
        grads = torch.autograd.grad(loss, self.parameters, materialize_grads=True)
        grad = torch.cat([grad.reshape(self.count, -1) for grad in grads], dim=1)
        return grad.mul_(self.gradient_mask) if self.masked else grad

    @property
    def count(self) -> int:
        return self.theta.shape[0]

    def layers(self, theta: torch.Tensor) -> list[list[Layer]]:
        """Per chain, per layer, views (K, M_c, rows, columns) of its tensors in ``theta`` (K, P)."""
        chains, offset = [], 0
        for chain in self.chains:
            layers, heads = [], len(chain.heads)
            for shapes in self.tensor_shapes(chain):
                tensors = []
                for rows, columns in shapes:
                    tensors.append(theta[:, offset:offset + heads * rows * columns].view(-1, heads, rows, columns))
                    offset += heads * rows * columns
                layers.append(tuple(tensors))
            chains.append(layers)
        return chains

    def chain_parameters(self) -> list[list[Layer]]:
        """The trainable leaf views of ``layers(theta)``."""
        tensors = iter(self.parameters)
        return [[tuple(next(tensors) for _ in shapes) for shapes in self.tensor_shapes(chain)] for chain in self.chains]

    def load(self, k: int, model: StateSpaceModel, mask: torch.Tensor) -> None:
        """Copy the parameters of ``model`` into row k; set its entries of ``mask`` (K, P) to 1."""
        with torch.no_grad():
            for chain, layers, mask_layers in zip(self.chains, self.chain_parameters(), self.layers(mask), strict=True):
                for position, h in enumerate(chain.heads):
                    net = model.nets[self.heads[h].name]
                    linears = [layer for layer in net.children() if isinstance(layer, torch.nn.Linear)]
                    norms: list[torch.nn.LayerNorm | None] = [
                        layer for layer in net.children() if isinstance(layer, torch.nn.LayerNorm)]
                    norms += [None] * (len(linears) - len(norms))
                    for tensors, masks, linear, norm in zip(layers, mask_layers, linears, norms, strict=True):
                        values = [linear.weight.T, linear.bias[None]]
                        if norm is not None:
                            values += [norm.weight[None], norm.bias[None]]
                        for tensor, tensor_mask, value in zip(tensors, masks, values, strict=True):
                            tensor[k, position, :value.shape[0], :value.shape[1]] = value
                            tensor_mask[k, position, :value.shape[0], :value.shape[1]] = 1.0

    def heads_forward(self, zv: torch.Tensor, theta: torch.Tensor | None, units: list[Units]
                      ) -> tuple[list[torch.Tensor], list[list[tuple[torch.Tensor, ...]]]]:
        """Output (K, out, B) of every head for zv = (z, v) (K, n + m, B), with the trained parameters or the
        rows of ``theta`` (K, P) (models with hidden ``units``); and per chain, what each hidden layer keeps for
        ``energy_gradient``, feature-major: its activation's input t (K M_c, width, B) and, with LayerNorm, the
        normalised units and 1 / their spread (K M_c, 1, B). One formula for every number of rows: a model's
        rounding never depends on how many others train or are scored beside it."""
        outputs: list[torch.Tensor | None] = [None] * len(self.heads)
        kept: list[list[tuple[torch.Tensor, ...]]] = []
        chains = self.chain_parameters() if theta is None else self.layers(theta)
        for c, (chain, layers) in enumerate(zip(self.chains, chains, strict=True)):
            x = zv if chain.in_dim > self.n else zv[:, :self.n]
            x = x.unsqueeze(1).expand(-1, len(chain.heads), -1, -1).flatten(0, 1)  # (K M_c, in, B)
            mask = units[c].mask.flatten(0, 1) if self.padded[c] else None
            inverse = units[c].inverse.flatten(0, 1)
            chain_kept: list[tuple[torch.Tensor, ...]] = []
            for weight, bias, *norm in layers[:-1]:
                a = torch.baddbmm(feature_major(bias), feature_major(weight), x)
                if not norm:
                    x = torch.tanh(a)
                    chain_kept.append((x,))
                    continue
                normalized, spread = masked_layer_norm(a, mask, inverse, dim=-2)
                t = torch.addcmul(feature_major(norm[1]), normalized, feature_major(norm[0]))
                x = functional.silu(t)
                chain_kept.append((t, normalized, spread))
            weight, bias = layers[-1]
            out = torch.baddbmm(feature_major(bias), feature_major(weight), x).view(
                zv.shape[0], len(chain.heads), -1, zv.shape[2])
            for h, head_out in zip(chain.heads, out.unbind(1), strict=True):
                outputs[h] = head_out[:, :self.heads[h].out_dim]
            kept.append(chain_kept)
        return cast(list[torch.Tensor], outputs), kept  # every head is one chain's

    def forward(self, zv: torch.Tensor, theta: torch.Tensor | None = None,
                models: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (K, n, B) and y (K, m, B) for zv = (z, v) (K, n + m, B) of every model training, or of
        parameters ``theta`` (K, P) of the given ``models`` (indices of the models the stack was built from;
        default: those training)."""
        units = self.units if models is None else [model_units.rows(models) for model_units in self.model_units]
        outputs, kept = self.heads_forward(zv, theta, units)
        v = zv[:, self.n:]
        named = {head.name: out for head, out in zip(self.heads, outputs, strict=True)}
        grad = None
        if self.architecture.energy_head is not None:
            grad = self.energy_gradient(named.pop(self.architecture.energy_head), kept, theta, units)
        return self.architecture.assemble(named, v, grad, FEATURE_MAJOR)

    def energy_gradient(self, energy_out: torch.Tensor, kept: list, theta: torch.Tensor | None,
                        units: list[Units]) -> torch.Tensor:
        """grad_z H (K, n, B), back-propagated through the energy head from its output (K, k, B): per hidden
        layer, SiLU' (t) = s (1 + t (1 - s)) with s = sigmoid(t) (tanh' = 1 - tanh^2), and LayerNorm's
        backward g -> (g^ - mean g^ - x^ mean(g^ x^)) / spread with g^ = g scale, means over the model's units."""
        h = next(index for index, head in enumerate(self.heads) if head.name == self.architecture.energy_head)
        c = next(index for index, chain in enumerate(self.chains) if h in chain.heads)
        position, chain = self.chains[c].heads.index(h), self.chains[c]
        layers = (self.chain_parameters() if theta is None else self.layers(theta))[c]
        per_head = lambda tensor: tensor.view(-1, len(chain.heads), *tensor.shape[1:])[:, position]  # noqa: E731
        out_weight = layers[-1][0][:, position, :, :energy_out.shape[1]]  # (K, width, k)
        g = out_weight @ self.architecture.energy_slope(energy_out)  # (K, width, B)
        inverse = units[c].inverse[:, position]  # (K, 1, 1)
        for (weight, _, *norm), saved in zip(layers[-2::-1], kept[c][::-1], strict=True):
            if norm:
                t, normalized, spread = (per_head(tensor) for tensor in saved)
                s = torch.sigmoid(t)
                g_hat = g * (s * (1 + t * (1 - s))) * norm[0][:, position].transpose(1, 2)
                mean_g = g_hat.sum(dim=-2, keepdim=True) * inverse
                mean_gx = (g_hat * normalized).sum(dim=-2, keepdim=True) * inverse
                g = (g_hat - mean_g - normalized * mean_gx) * spread
            else:
                x = per_head(saved[0])
                g = g * (1 - x.square())
            g = weight[:, position] @ g  # (K, in, B)
        return g[:, :self.n]

