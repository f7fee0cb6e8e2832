"""Scores of trained input-output models on every test record of their benchmark, all models of a lockstep group at
once, in float64 numpy (a step of these tiny MLPs costs a few microseconds there, tens in torch).

Every model is simulated freely (its own outputs fed back; the first ``init`` samples of a record are the
measured ones) and a NARX model also one step ahead (measured past outputs). Columns are named
``<metric>_<mode>_<record>``: metric nmae, nmse, rmse_mv (RMSE in mV), spread (the predicted output's standard
deviation over the measured one's; NaN where the prediction is not finite) or finite (1 where every predicted
sample is finite, else 0), mode free_run or one_step, the record as the system's ``tests`` name it (e.g.
``nmae_free_run_arrow_full``); and ``nmae_mean_predictor_<record>``, ``nmse_mean_predictor_<record>``: the scores of
the constant output at the training prefix's mean, the level a model that learned nothing reaches.
"""

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from nsl_hpc.models.blocks import LAYER_NORM_EPS
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.data import Signals
from nsl_hpc.studies.input_output.stacked import StackedMLPs, split_bypass
from nsl_hpc.studies.input_output.training import SignalScaling
from nsl_hpc.studies.metrics import normalized_errors

CHUNK = 4096  # time steps whose inputs' part of the first layer is computed at once
MODES = ("free_run", "one_step")


@dataclass(frozen=True)
class NumpyLayer:
    """One layer of K MLPs in float64: weight (K, in, out), bias (K, 1, out) and, for a hidden layer, its
    activation: LayerNorm over each model's own units (``units``: mask (K, 1, out), 1 / their number
    (K, 1, 1)) with scale and shift (``norm``, (K, 1, out) each) then SiLU, or tanh when ``norm`` is None."""

    weight: np.ndarray
    bias: np.ndarray
    norm: tuple[np.ndarray, np.ndarray] | None = None
    units: tuple[np.ndarray, np.ndarray] | None = None

    def activate(self, pre: np.ndarray) -> np.ndarray:
        """The hidden activation of the pre-activation ``pre`` (K, B, out)."""
        if self.norm is None:
            return np.tanh(pre)
        if self.units is None:
            raise ValueError("a LayerNorm layer needs its models' units")
        mask, inverse = self.units
        centered = (pre - pre.sum(axis=-1, keepdims=True) * inverse) * mask
        scale, shift = self.norm
        t = centered / np.sqrt(np.square(centered).sum(axis=-1, keepdims=True) * inverse + LAYER_NORM_EPS)
        t = t * scale + shift
        return t / (1.0 + np.exp(-t))


@dataclass(frozen=True)
class NumpyMLP:
    """K MLPs in float64: their ``layers`` (hidden, then output) and the weight (K, in, out) of their bypass
    (None: none)."""

    layers: list[NumpyLayer]
    bypass: np.ndarray | None = None

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """Outputs (K, B, out) of inputs z (K, B, in)."""
        out = hidden(self.layers, z @ self.layers[0].weight + self.layers[0].bias)
        return out if self.bypass is None else out + z @ self.bypass


def numpy_mlps(nets: StackedMLPs, theta: torch.Tensor) -> dict[str, NumpyMLP]:
    """The MLPs of the group's models with parameters ``theta`` (K, P), every model it was built from, in
    float64."""
    mask, inverse = (tensor.double().numpy() for tensor in nets.model_units)
    units = (mask, inverse)
    mlps = {}
    for name, stacked in nets.layers(theta.detach().double()).items():
        layers, bypass = split_bypass(stacked)
        arrays = [[tensor.numpy() for tensor in layer] for layer in layers]
        numpy_layers = [NumpyLayer(weight, bias, (norm[0], norm[1]) if norm else None, units)
                        for weight, bias, *norm in arrays[:-1]]
        numpy_layers.append(NumpyLayer(arrays[-1][0], arrays[-1][1]))
        mlps[name] = NumpyMLP(numpy_layers, None if bypass is None else bypass.numpy())
    return mlps


def hidden(layers: list[NumpyLayer], first: np.ndarray) -> np.ndarray:
    """The MLPs' output (K, B, out) given their first layer's pre-activation ``first`` (K, B, width)."""
    h = layers[0].activate(first)
    for layer in layers[1:-1]:
        h = layer.activate(h @ layer.weight + layer.bias)
    return h @ layers[-1].weight + layers[-1].bias


def narx_parts(net: NumpyMLP, past_outputs: int) -> tuple[np.ndarray, np.ndarray]:
    """F's first layer and bypass side by side, (K, n_y + n_u + 1, width + 1) (the last column the bypass, 0
    without one), split into the rows of the past outputs and of the inputs: both parts of a regressor's
    contribution come from one product."""
    first = net.layers[0].weight
    bypass = np.zeros((*first.shape[:-1], 1)) if net.bypass is None else net.bypass
    joined = np.concatenate([first, bypass], axis=-1)
    return joined[:, :past_outputs], joined[:, past_outputs:]


def narx_output(net: NumpyMLP, pre: np.ndarray) -> np.ndarray:
    """F's output (K, B) from ``pre`` (K, B, width + 1): its first layer's pre-activation without the bias, and
    the bypass's output in the last column (``narx_parts``)."""
    return hidden(net.layers, pre[..., :-1] + net.layers[0].bias)[..., 0] + pre[..., -1]


def simulate_narx(net: NumpyMLP, past_outputs: int, past_inputs: int, u: np.ndarray, y: np.ndarray,
                  init: int) -> np.ndarray:
    """Free-run simulation (K, N) on standardised u, y (K, N) of K NARX models' F (``net``, its bypass included):
    y_0..y_{init-1} are given, every later output is predicted from the model's own past predictions.
    ``init`` >= max(n_y, n_u)."""
    w_y, w_u = narx_parts(net, past_outputs)
    windows = np.lib.stride_tricks.sliding_window_view(u, past_inputs + 1, axis=1)  # window j: u_j..u_{j+n_u}
    simulated = y.astype(float).copy()
    for begin in range(init, u.shape[1], CHUNK):
        stop = min(begin + CHUNK, u.shape[1])
        from_inputs = windows[:, begin - past_inputs:stop - past_inputs] @ w_u  # (K, chunk, width + 1)
        for j, t in enumerate(range(begin, stop)):
            pre = from_inputs[:, j:j + 1] + simulated[:, None, t - past_outputs:t] @ w_y
            simulated[:, t] = narx_output(net, pre)[:, 0]
    return simulated


def one_step_narx(net: NumpyMLP, past_outputs: int, past_inputs: int, u: np.ndarray, y: np.ndarray,
                  init: int) -> np.ndarray:
    """One-step-ahead predictions (K, N) on standardised u, y (K, N) of K NARX models' F (``net``): y_t from the
    measured y_{t-n_y..t-1} and u_{t-n_u..t}, for t >= ``init``; the first ``init`` samples are the measured
    ones."""
    w_y, w_u = narx_parts(net, past_outputs)
    u_windows = np.lib.stride_tricks.sliding_window_view(u, past_inputs + 1, axis=1)
    y_windows = np.lib.stride_tricks.sliding_window_view(y, past_outputs, axis=1)  # window j: y_j..y_{j+n_y-1}
    predicted = y.astype(float).copy()
    for begin in range(init, u.shape[1], CHUNK):
        stop = min(begin + CHUNK, u.shape[1])
        pre = (u_windows[:, begin - past_inputs:stop - past_inputs] @ w_u
               + y_windows[:, begin - past_outputs:stop - past_outputs] @ w_y)
        predicted[:, begin:stop] = narx_output(net, pre)
    return predicted


def simulate_subnet(mlps: Mapping[str, NumpyMLP], state_dim: int, past: int, residual: bool, u: np.ndarray,
                    y: np.ndarray, init: int) -> np.ndarray:
    """Free-run simulation (K, N) on standardised u, y (K, N): the encoder reads the ``past`` samples before
    index ``init`` (init >= P), then x_{k+1} = x_k + f(x_k, u_k) (``residual``) or f(x_k, u_k), y_k = h(x_k)."""
    encoder, f, h = mlps["encoder"], mlps["f"], mlps["h"]
    x = encoder(np.concatenate([u[:, init - past:init], y[:, init - past:init]], axis=1)[:, None])  # (K, 1, n_x)
    first = f.layers[0]
    w_x, w_u = first.weight[:, :state_dim], first.weight[:, state_dim:]  # (K, n_x, width), (K, 1, width)
    simulated = y.astype(float).copy()
    for begin in range(init, u.shape[1], CHUNK):
        stop = min(begin + CHUNK, u.shape[1])
        from_inputs = u[:, begin:stop, None] * w_u + first.bias  # (K, chunk, width)
        if f.bypass is not None:
            bypass_inputs = u[:, begin:stop, None] * f.bypass[:, state_dim:]  # (K, chunk, n_x)
        for j in range(stop - begin):
            simulated[:, begin + j] = h(x)[:, 0, 0]
            change = hidden(f.layers, from_inputs[:, j:j + 1] + x @ w_x)
            if f.bypass is not None:
                change = change + bypass_inputs[:, j:j + 1] + x @ f.bypass[:, :state_dim]
            x = x + change if residual else change
    return simulated


def predictions(model: NARX | SUBNET, mlps: Mapping[str, NumpyMLP], u: np.ndarray, y: np.ndarray,
                init: int) -> dict[str, np.ndarray]:
    """Standardised outputs (K, N) of the models (of ``model``'s architecture) by mode."""
    if isinstance(model, NARX):
        args = (mlps["net"], model.past_outputs, model.past_inputs, u, y, init)
        return {"free_run": simulate_narx(*args), "one_step": one_step_narx(*args)}
    return {"free_run": simulate_subnet(mlps, model.state_dim, model.past, model.residual, u, y, init)}


def score_records(model: NARX | SUBNET, mlps: Mapping[str, NumpyMLP], scalings: Sequence[SignalScaling],
                  tests: Mapping[str, Signals], init: int, mv_per_unit: float) -> list[dict[str, float]]:
    """Per model (K, in the order of ``scalings``), its scores on every test record by name: nmae, nmse and
    rmse_mv (RMSE times ``mv_per_unit``) of each mode, counted after the first ``init`` samples."""
    rows: list[dict[str, float]] = [{} for _ in scalings]
    for record_name, record in tests.items():
        u = np.stack([scaling.normalise(record)[0] for scaling in scalings])
        y = np.stack([scaling.normalise(record)[1] for scaling in scalings])
        measured = record.y[init:]
        with np.errstate(all="ignore"):  # a diverged or unstable model's simulation overflows to inf / NaN
            by_mode = predictions(model, mlps, u, y, init)
            for mode, standardised in by_mode.items():
                for row, scaling, output in zip(rows, scalings, standardised, strict=True):
                    predicted = output[init:] * scaling.y_std + scaling.y_mean
                    row.update(output_scores(measured, predicted, mv_per_unit, f"{mode}_{record_name}"))
        for row, scaling in zip(rows, scalings, strict=True):
            constant = np.full((len(measured), 1), scaling.y_mean)
            row.update({f"{metric}_mean_predictor_{record_name}": value
                        for metric, value in normalized_errors(measured[:, None], constant).items()})
    return rows


def output_scores(measured: np.ndarray, predicted: np.ndarray, mv_per_unit: float, name: str) -> dict[str, float]:
    """nmae, nmse, rmse_mv, spread and finite (the module's columns) of ``predicted`` against ``measured`` (N,),
    each named ``<metric>_<name>``."""
    finite = bool(np.isfinite(predicted).all())
    scores = normalized_errors(measured[:, None], predicted[:, None])
    scores["rmse_mv"] = mv_per_unit * float(np.sqrt(np.mean(np.square(predicted - measured))))
    scores["spread"] = float(predicted.std() / measured.std()) if finite else math.nan
    scores["finite"] = float(finite)
    return {f"{metric}_{name}": value for metric, value in scores.items()}
