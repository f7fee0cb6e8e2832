"""NARX and SUBNET: documented shapes, parameter counts, an encoder that sees only the past, and numpy free-run
and one-step predictions of a pack of models equal to each torch model run step by step."""

import numpy as np
import pytest
import torch

from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.scoring import numpy_mlps, one_step_narx, simulate_narx, simulate_subnet
from nsl_hpc.studies.input_output.stacked import StackedMLPs
from tests.helpers import mlp_parameter_count

B, P, T, NX = 7, 50, 13, 4


@pytest.fixture
def subnet() -> SUBNET:
    torch.manual_seed(0)
    return SUBNET(state_dim=NX, past=P, width=8, depth=2, block="layernorm_silu").double()


def test_subnet_forward_has_the_documented_shapes(subnet):
    past_u, past_y, future_u = torch.randn(B, P, dtype=torch.double), torch.randn(B, P, dtype=torch.double), \
        torch.randn(B, T, dtype=torch.double)
    assert subnet.encode(past_u, past_y).shape == (B, NX)
    assert subnet(past_u, past_y, future_u).shape == (B, T)


def test_subnet_encoder_sees_only_the_past(subnet):
    """Changing u_t.. or any later input leaves the state x_t and the first simulated output y_t alone;
    changing y_{t-1} or u_{t-1} moves them; the output at step k depends on u_t..u_{t+k-1} only."""
    rng = torch.Generator().manual_seed(1)
    u = torch.randn(B, P + T, generator=rng, dtype=torch.double)
    y = torch.randn(B, P + T, generator=rng, dtype=torch.double)
    reference = subnet(u[:, :P], y[:, :P], u[:, P:])
    changed_future = u.clone()
    changed_future[:, P + 5:] += 1.0  # u_{t+5} onwards
    changed = subnet(u[:, :P], y[:, :P], changed_future[:, P:])
    assert torch.equal(changed[:, :6], reference[:, :6]) and not torch.allclose(changed[:, 6:], reference[:, 6:])
    changed_past = y.clone()
    changed_past[:, P - 1] += 1.0  # y_{t-1}
    assert not torch.allclose(subnet(u[:, :P], changed_past[:, :P], u[:, P:])[:, 0], reference[:, 0])


def test_parameter_counts_leave_out_the_encoder_only(subnet):
    """The paper's layout: the bypasses of h (n_x weights) and of the encoder (2 P n_x) count as their MLPs do;
    deepSI's: f's bypass, (n_x + 1) n_x weights, counts too."""
    f = mlp_parameter_count(NX + 1, NX, 8, 2, "layernorm_silu")
    h = mlp_parameter_count(NX, 1, 8, 2, "layernorm_silu") + NX
    encoder = mlp_parameter_count(2 * P, NX, 8, 2, "layernorm_silu") + 2 * P * NX
    assert subnet.counted_parameters() == f + h
    assert sum(p.numel() for p in subnet.parameters()) == f + h + encoder
    deepsi = SUBNET(NX, P, 8, 2, "tanh", bypass=("encoder", "f", "h"), residual=False, zero_bias=True)
    assert deepsi.counted_parameters() == (mlp_parameter_count(NX + 1, NX, 8, 2, "tanh") + (NX + 1) * NX
                                           + mlp_parameter_count(NX, 1, 8, 2, "tanh") + NX)
    assert all(not layer.bias.any() for layer in deepsi.modules()
               if isinstance(layer, torch.nn.Linear) and layer.bias is not None)
    assert NARX(50, 50, 8, 3, "tanh").counted_parameters() == mlp_parameter_count(101, 1, 8, 3, "tanh")


@pytest.mark.parametrize("bypass", [("encoder", "h"), ("encoder", "f", "h")])
def test_a_residual_f_with_a_zeroed_output_starts_at_the_identity(bypass):
    """zero_f_output zeroes f's last layer and, where f has one, its bypass: x_{k+1} = x_k at initialisation."""
    model = SUBNET(NX, P, 8, 2, "tanh", bypass=bypass, residual=True, zero_f_output=True)
    x, u = torch.randn(5, NX), torch.randn(5, 1)
    assert torch.equal(model.step(x, u), x)
    assert not torch.equal(SUBNET(NX, P, 8, 2, "tanh", bypass=bypass, residual=True).step(x, u), x)


def test_narx_maps_its_regressors_to_one_output():
    """y_t = F(y_{t-5..t-1}, u_{t-3..t}): one output per sample, from that sample's regressors alone, every one
    of which counts (the current input u_t included)."""
    torch.manual_seed(0)
    model = NARX(past_outputs=5, past_inputs=3, width=6, depth=1, block="layernorm_silu")
    past_y, inputs = torch.randn(B, 5), torch.randn(B, 4)
    with torch.no_grad():
        y = model(past_y, inputs)
        assert y.shape == (B,)
        assert torch.equal(y, model.net(torch.cat([past_y, inputs], dim=-1))[:, 0])
        assert torch.allclose(model(past_y[:1], inputs[:1]), y[:1])  # a sample's output is its own
        for column in range(9):  # each regressor moves the output
            shifted = torch.cat([past_y, inputs], dim=-1)
            shifted[:, column] += 1.0
            assert not torch.allclose(model(shifted[:, :5], shifted[:, 5:]), y)


def numpy_of(*models) -> dict:
    """The float64 numpy MLPs of ``models`` packed (zero-padded to the widest)."""
    nets = StackedMLPs(list(models), torch.float64)
    return numpy_mlps(nets, nets.theta)


@pytest.mark.parametrize(("block", "bypass", "residual"), [
    ("layernorm_silu", ("encoder", "h"), True), ("tanh", ("encoder", "h"), True), ("layernorm_silu", (), True),
    ("tanh", ("encoder", "f", "h"), False)])
def test_numpy_free_run_of_a_pack_equals_each_torch_model_step_by_step(block, bypass, residual):
    """Two models of different widths simulated together (the narrower zero-padded) give what each torch
    module gives alone, with or without bypasses and the residual."""
    rng = np.random.default_rng(2)
    u, y = rng.standard_normal(P + 40), rng.standard_normal(P + 40)
    subnets = []
    for seed, width in ((0, 8), (1, 5)):
        torch.manual_seed(seed)
        subnets.append(SUBNET(NX, P, width, 2, block, bypass, residual).double())
        for parameter in subnets[-1].parameters():  # LayerNorm scales and shifts away from 1 and 0 too
            parameter.data.normal_(0, 0.3)
    simulated = simulate_subnet(numpy_of(*subnets), NX, P, residual, np.stack([u, u]), np.stack([y, y]), P)
    for subnet, row in zip(subnets, simulated, strict=True):
        with torch.no_grad():
            expected = subnet(torch.tensor(u[None, :P]), torch.tensor(y[None, :P]), torch.tensor(u[None, P:]))[0]
        np.testing.assert_allclose(row[P:], expected.numpy(), rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(row[:P], y[:P])


@pytest.mark.parametrize(("block", "bypass"), [("layernorm_silu", False), ("tanh", False), ("layernorm_silu", True),
                                               ("tanh", True)])
def test_numpy_narx_scoring_of_a_pack_equals_each_torch_model_fed_its_own_outputs(block, bypass):
    """Two NARX models of different widths (the narrower zero-padded), their bypasses included, simulated freely
    and one step ahead in numpy give what each torch module gives fed back its own outputs, or the measured ones."""
    rng = np.random.default_rng(2)
    u, y = rng.standard_normal(P + 40), rng.standard_normal(P + 40)
    narxes = []
    for seed, width in ((3, 5), (4, 2)):
        torch.manual_seed(seed)
        narxes.append(NARX(past_outputs=6, past_inputs=4, width=width, depth=2, block=block, bypass=bypass).double())
        for parameter in narxes[-1].parameters():
            parameter.data.normal_(0, 0.3)
    mlps = numpy_of(*narxes)
    assert (mlps["net"].bypass is not None) == bypass
    simulated = simulate_narx(mlps["net"], 6, 4, np.stack([u, u]), np.stack([y, y]), init=P)
    one_step = one_step_narx(mlps["net"], 6, 4, np.stack([u, u]), np.stack([y, y]), init=P)
    for narx, free_row, one_step_row in zip(narxes, simulated, one_step, strict=True):
        fed_back, measured_past = y.copy(), y.copy()
        with torch.no_grad():
            for t in range(P, len(u)):
                fed_back[t] = narx(torch.tensor(fed_back[None, t - 6:t]), torch.tensor(u[None, t - 4:t + 1])).item()
                measured_past[t] = narx(torch.tensor(y[None, t - 6:t]), torch.tensor(u[None, t - 4:t + 1])).item()
        np.testing.assert_allclose(free_row, fed_back, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(one_step_row, measured_past, rtol=1e-10, atol=1e-12)


def test_a_width_1_narx_with_its_bypass_depends_on_every_regressor():
    """One hidden unit behind LayerNorm is a constant: without the bypass such an F ignores its input; with it,
    each regressor moves the output (the linear dynamics a NARX of the study's smallest width tier captures)."""
    z = torch.randn(B, 10)
    for bypass, moves in ((False, False), (True, True)):
        torch.manual_seed(0)
        model = NARX(past_outputs=6, past_inputs=3, width=1, depth=1, block="layernorm_silu", bypass=bypass)
        with torch.no_grad():
            y = model(z[:, :6], z[:, 6:])
            for column in range(10):
                shifted = z.clone()
                shifted[:, column] += 1.0
                assert (not torch.allclose(model(shifted[:, :6], shifted[:, 6:]), y)) == moves


def test_narx_counts_its_bypass_and_starts_its_biases_at_zero():
    """p counts F's bypass (n_y + n_u + 1 weights): the study's smallest NARX, n_h 1, n_d 1, tanh, 205 parameters
    (104 without the bypass); zero_bias starts every bias at 0."""
    assert NARX(50, 50, 1, 1, "tanh", bypass=True).counted_parameters() == 205
    assert NARX(50, 50, 1, 1, "tanh").counted_parameters() == 104
    model = NARX(50, 50, 8, 2, "tanh", bypass=True, zero_bias=True)
    assert all(not layer.bias.any() for layer in model.net if isinstance(layer, torch.nn.Linear))
    assert model.bypass is not None and model.bypass.bias is None

