"""K NARX or SUBNET MLP sets of one architecture, depth and block as batched MLPs (``StackedMLPs``): every
parameter of a model is one row of ``theta`` (K, P), zero-padded to the widest hidden width; LayerNorm averages
over each model's own units and padded entries get exactly zero gradient, so a padded model computes and learns
what it does alone (``input_output.lockstep`` trains them; ``input_state.stacked`` is the input-state stack).
"""

from collections.abc import Mapping, Sequence
from typing import cast

import torch
from torch import nn
from torch.nn import functional

from nsl_hpc.models.blocks import LAYER_NORM_EPS, masked_layer_norm
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET

# A compiled batch-major stack computes a product with at most this many output columns (f's and h's last layers:
# n_x, 1) as its transpose, (K, columns, B): MKL's batched GEMM writes few long rows several times faster than many
# rows of a few columns ((8, 256, 32) x (8, 32, 4): 62 against 14 us; its weight gradient 80 against 11 us); at 16
# columns the two are even. Eagerly the transposed layouts it passes on cost more than that (K = 8, 32 x 3: 14-18%
# slower).
NARROW_OUTPUTS = 8

# A layer's tensors: weight (K, in, out), bias (K, 1, out)[, LayerNorm scale, shift (K, 1, out)]; a bypass, the
# last layer of an MLP that has one: its weight (K, in, out) alone
Layer = tuple[torch.Tensor, ...]


def mlp_shape(net: nn.Sequential, bypass: nn.Linear | None) -> tuple[int, int, int, bool, bool]:
    """(inputs, outputs, depth, LayerNorm, bypass) of an MLP of ``nsl_hpc.models.blocks.mlp`` and its bypass."""
    linears = [layer for layer in net if isinstance(layer, nn.Linear)]
    return (linears[0].in_features, linears[-1].out_features, len(linears) - 1,
            any(isinstance(layer, nn.LayerNorm) for layer in net), bypass is not None)


def mlp_shapes(model: NARX | SUBNET) -> dict[str, tuple[int, int, int, bool, bool]]:
    """``mlp_shape`` of each MLP of ``model`` by name."""
    bypasses = model.bypasses()
    return {name: mlp_shape(net, bypasses.get(name)) for name, net in model.mlps().items()}


def split_bypass(layers: list[Layer]) -> tuple[list[Layer], torch.Tensor | None]:
    """An MLP's layers without its bypass, and the bypass weight (None without one)."""
    return (layers[:-1], layers[-1][0]) if len(layers[-1]) == 1 else (layers, None)


class StackedMLPs:
    """The MLPs of K models of one architecture, depth and block as batched MLPs; ``theta`` (K, P) holds every
    parameter, zero-padded to the widest hidden width ``width``. Their activations are stored feature-major when
    there are several models no wider than ``feature_major_width``, batch-major otherwise; a feature-major stack,
    or one whose step is ``compiled``, computes with ``centred`` LayerNorm weights; a compiled batch-major stack
    computes its products of few output columns as their transposes (``linear``)."""

    def __init__(self, models: Sequence[NARX | SUBNET], dtype: torch.dtype, feature_major_width: int = 0,
                 compiled: bool = False):
        self.shapes = mlp_shapes(models[0])
        if any(mlp_shapes(model) != self.shapes for model in models):
            raise ValueError(f"models trained together need one architecture, depth and block ({type(models[0])}, "
                             f"MLPs {self.shapes}); widths may differ")
        own = [cast(nn.Linear, next(iter(model.mlps().values()))[0]).out_features for model in models]
        self.width = max(own)
        self.alone = len(models) == 1
        self.feature_major = not self.alone and self.width <= feature_major_width  # for the group's whole life
        # LayerNorm layers compute from centred weights (``computed``), except eager batch-major stacks: torch's
        # fused LayerNorm is faster there
        self.centred = self.feature_major or compiled
        self.compiled = compiled
        # an activation's dimensions of the units and of the B windows
        self.features, self.samples = (-2, -1) if self.feature_major else (-1, -2)
        size = sum(rows * columns for name in self.shapes for layer in self.tensor_shapes(name)
                   for rows, columns in layer)
        self.use_theta(torch.zeros(len(models), size, dtype=dtype))
        mask = torch.zeros_like(self.theta)
        with torch.no_grad():
            for k, model in enumerate(models):
                self.load(k, model, mask)
        self.gradient_mask = mask  # (K, P): 0 on padding
        units = torch.tensor(own, dtype=dtype)
        # mask (K, 1, width) of each model's own units, 1 / their number (K, 1, 1): every model built from
        self.model_units = (torch.arange(self.width) < units[:, None]).to(dtype)[:, None], (1.0 / units)[:, None, None]
        self.train_models(torch.arange(len(models)))

    def train_models(self, models: torch.Tensor) -> None:
        """The rows of ``theta`` hold ``models`` (K',), indices of the models the stack was built from."""
        self.models = models
        mask, inverse = self.model_units
        self.padded = bool((mask[models] == 0).any())  # some model training is narrower than ``width``
        self.units = (mask[models] if self.padded else None, inverse[models])

    def tensor_shapes(self, name: str) -> list[list[tuple[int, int]]]:
        """(rows, columns) of each tensor of each layer of MLP ``name`` (its bypass last)."""
        inputs, outputs, depth, layer_norm, bypass = self.shapes[name]
        norm = [(1, self.width)] * 2 if layer_norm else []
        return [*([[(fan_in, self.width), (1, self.width), *norm]
                   for fan_in in [inputs] + [self.width] * (depth - 1)]),
                [(self.width, outputs), (1, outputs)], *([[(inputs, outputs)]] if bypass else [])]

    def layers(self, theta: torch.Tensor) -> dict[str, list[Layer]]:
        """Per MLP, per layer, views (K, rows, columns) of its tensors in ``theta`` (K, P)."""
        views, offset = {}, 0
        for name in self.shapes:
            layers = []
            for shapes in self.tensor_shapes(name):
                tensors = []
                for rows, columns in shapes:
                    tensors.append(theta[:, offset:offset + rows * columns].view(-1, rows, columns))
                    offset += rows * columns
                layers.append(tuple(tensors))
            views[name] = layers
        return views

    def computed(self, theta: torch.Tensor | None = None) -> dict[str, list[Layer]]:
        """The layers as the stack computes with them: ``trained``, or views of ``theta`` (K, P); when ``centred``,
        each LayerNorm layer's weight and bias centred over each model's own units (padding stays 0). The mean over
        a model's units of x W + b is x (W 1 / n) + mean(b), so the LayerNorm of x W + b is x W_c + b_c over its
        root mean square: one reduction fewer per hidden layer, forward and backward; only rounding differs."""
        layers = self.trained if theta is None else self.layers(theta)
        if not self.centred:
            return dict(layers)
        mask, inverse = self.units
        return {name: [tuple(self.centre(tensor, mask, inverse) for tensor in layer[:2]) + layer[2:]
                       if len(layer) == 4 else layer for layer in mlp] for name, mlp in layers.items()}

    @staticmethod
    def centre(tensor: torch.Tensor, mask: torch.Tensor | None, inverse: torch.Tensor) -> torch.Tensor:
        """A weight (K, in, width) or bias (K, 1, width) less its mean over each model's own units (``mask``
        (K, 1, width), None: all; ``inverse`` (K, 1, 1): 1 / their number); padded columns, 0, stay 0."""
        centred = tensor - tensor.sum(dim=-1, keepdim=True) * inverse
        return centred if mask is None else centred * mask

    def use_theta(self, theta: torch.Tensor) -> None:
        """Hold the parameters in ``theta`` (K, P); the trained layers are leaf views into it."""
        self.theta = theta
        self.trained = self.layers(theta)
        self.parameters = [tensor.requires_grad_(True) for layers in self.trained.values() for layer in layers
                           for tensor in layer]

    def load(self, k: int, model: NARX | SUBNET, mask: torch.Tensor) -> None:
        """Copy the parameters of ``model`` into row k; set its entries of ``mask`` (K, P) to 1."""
        masks = self.layers(mask)
        bypasses = model.bypasses()
        for name, net in model.mlps().items():
            linears = [layer for layer in net if isinstance(layer, nn.Linear)]
            norms = [layer for layer in net if isinstance(layer, nn.LayerNorm)] + [None] * len(linears)
            values = []
            for linear, norm in zip(linears, norms, strict=False):
                values.append([linear.weight.T, linear.bias[None]] + ([] if norm is None else
                                                                      [norm.weight[None], norm.bias[None]]))
            if name in bypasses:
                values.append([bypasses[name].weight.T])
            for tensors, mask_tensors, layer_values in zip(self.trained[name], masks[name], values, strict=True):
                for tensor, tensor_mask, value in zip(tensors, mask_tensors, layer_values, strict=True):
                    tensor[k, :value.shape[0], :value.shape[1]] = value
                    tensor_mask[k, :value.shape[0], :value.shape[1]] = 1.0

    def keep(self, rows: torch.Tensor) -> None:
        """Keep only the models of ``rows`` (K',): ``theta`` becomes a new (K', P) tensor."""
        self.use_theta(self.theta.detach()[rows])
        self.gradient_mask = self.gradient_mask[rows]
        self.train_models(self.models[rows])

    def parameter_gradient(self, loss: torch.Tensor) -> torch.Tensor:
        """d loss / d parameters (K, P), exactly 0 on padding entries."""
        grads = torch.autograd.grad(loss, self.parameters, materialize_grads=True)
        return torch.cat([grad.reshape(len(self.theta), -1) for grad in grads], dim=1).mul_(self.gradient_mask)

    def orient(self, tensor: torch.Tensor) -> torch.Tensor:
        """A parameter tensor (K, rows, columns) as the stack's layout multiplies or adds it: transposed when
        feature-major (a weight (K, out, in), a bias or LayerNorm affine (K, out, 1))."""
        return tensor.mT if self.feature_major else tensor

    def oriented(self, layers: Mapping[str, list[Layer]]) -> dict[str, list[Layer]]:
        """``layers`` (as ``layers`` gives them) with every tensor oriented: what ``run`` takes."""
        return {name: [tuple(self.orient(tensor) for tensor in layer) for layer in mlp] for name, mlp in layers.items()}

    def activations(self, x: torch.Tensor) -> torch.Tensor:
        """Inputs x (K, in, B) in the stack's layout: as they are, or (K, B, in) batch-major."""
        return x if self.feature_major else x.mT

    def run(self, x: torch.Tensor, layers: list[Layer], first: torch.Tensor | None = None,
            bypassed: torch.Tensor | None = None) -> torch.Tensor:
        """Output of one MLP, its ``layers`` oriented, for inputs x (plus its bypass of x), or from its first
        layer's pre-activation ``first`` and its bypass's output ``bypassed`` (then x is not read; None: no bypass);
        activations in the stack's layout: (K, features, B) or (K, B, features)."""
        layers, bypass = split_bypass(layers)
        if first is None and bypass is not None:
            bypassed = self.linear(x, bypass, None)
        for weight, bias, *norm in layers[:-1]:
            a = self.linear(x, weight, bias) if first is None else first
            first, x = None, self.activate(a, norm)
        weight, bias = layers[-1]
        return self.linear(x, weight, bias if bypassed is None else bias + bypassed)

    def linear(self, x: torch.Tensor, weight: torch.Tensor, added: torch.Tensor | None) -> torch.Tensor:
        """An oriented ``weight`` applied to x plus ``added`` (an oriented bias, or a pre-activation part; None:
        nothing); a compiled batch-major stack computes a product of at most ``NARROW_OUTPUTS`` columns as its
        transpose."""
        if added is None:
            return torch.bmm(weight, x) if self.feature_major else torch.bmm(x, weight)
        if self.feature_major:
            return torch.baddbmm(added, weight, x)
        if self.compiled and weight.shape[-1] <= NARROW_OUTPUTS:
            return torch.baddbmm(added.mT, weight.mT, x.mT).mT
        return torch.baddbmm(added, x, weight)

    def activate(self, a: torch.Tensor, norm: list[torch.Tensor]) -> torch.Tensor:
        """A hidden layer's activation of its pre-activation a: tanh, or LayerNorm over each model's own units
        with its oriented scale and shift, then SiLU. When ``centred`` a is already centred (``computed``) and
        the LayerNorm divides it by its root mean square; else (batch-major, eager) torch's fused LayerNorm where
        every model uses all units (with the affine part for a model alone, as its module), or the masked
        formula of ``masked_layer_norm``."""
        if not norm:
            return torch.tanh(a)
        scale, shift = norm
        if self.centred:  # padded units of a are 0
            mean_square = a.square().sum(dim=self.features, keepdim=True) * self.units[1]
            normalized = a * (mean_square + LAYER_NORM_EPS).rsqrt()
        elif self.alone:
            return functional.silu(functional.layer_norm(a, a.shape[-1:], scale.view(-1), shift.view(-1),
                                                         LAYER_NORM_EPS))
        elif self.padded:
            normalized, _ = masked_layer_norm(a, self.units[0], self.units[1])
        else:  # every model as wide as the stack: torch's fused LayerNorm without its affine part
            normalized = functional.layer_norm(a, a.shape[-1:], eps=LAYER_NORM_EPS)
        return functional.silu(torch.addcmul(shift, normalized, scale))
