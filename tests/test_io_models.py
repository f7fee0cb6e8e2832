"""NARX and SUBNET: documented shapes, parameter counts, an encoder that sees only the past, and a numpy
free-run simulation equal to the torch models run step by step."""

import numpy as np
import pytest
import torch

from nsl_hpc.models.blocks import mlp_parameter_count
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.training import simulate_narx, simulate_subnet

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
    f = mlp_parameter_count(NX + 1, NX, 8, 2, "layernorm_silu")
    h = mlp_parameter_count(NX, 1, 8, 2, "layernorm_silu")
    assert subnet.counted_parameters() == f + h
    assert sum(p.numel() for p in subnet.parameters()) == f + h + mlp_parameter_count(2 * P, NX, 8, 2, "layernorm_silu")
    assert NARX(50, 50, 8, 3, "tanh").counted_parameters() == mlp_parameter_count(101, 1, 8, 3, "tanh")


def test_narx_maps_its_regressors_to_one_output():
    model = NARX(past_outputs=5, past_inputs=3, width=6, depth=1, block="layernorm_silu")
    assert model(torch.randn(B, 5), torch.randn(B, 4)).shape == (B,)


@pytest.mark.parametrize("block", ["layernorm_silu", "tanh"])
def test_numpy_free_run_equals_the_torch_models_step_by_step(block):
    torch.manual_seed(0)
    subnet = SUBNET(state_dim=NX, past=P, width=8, depth=2, block=block).double()
    for parameter in subnet.parameters():  # LayerNorm scales and shifts away from 1 and 0 too
        parameter.data.normal_(0, 0.3)
    rng = np.random.default_rng(2)
    u, y = rng.standard_normal(P + 40), rng.standard_normal(P + 40)
    with torch.no_grad():
        expected = subnet(torch.tensor(u[None, :P]), torch.tensor(y[None, :P]), torch.tensor(u[None, P:]))[0].numpy()
    np.testing.assert_allclose(simulate_subnet(subnet, u, y, P)[P:], expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(simulate_subnet(subnet, u, y, P)[:P], y[:P])

    torch.manual_seed(3)
    narx = NARX(past_outputs=6, past_inputs=4, width=5, depth=2, block=block).double()
    simulated = simulate_narx(narx, u, y, init=P)
    fed_back = y.copy()
    with torch.no_grad():
        for t in range(P, len(u)):
            fed_back[t] = narx(torch.tensor(fed_back[None, t - 6:t]), torch.tensor(u[None, t - 4:t + 1])).item()
    np.testing.assert_allclose(simulated, fed_back, rtol=1e-10, atol=1e-12)
