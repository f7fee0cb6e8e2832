"""Architectures: port-Hamiltonian structure for any parameters, and the parameter-count relation."""

import pytest
import torch
from omegaconf import OmegaConf

from nsl_hpc.cli import compose_config
from nsl_hpc.errors import ConfigError
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import mlp, mlp_parameter_count, parameter_count
from nsl_hpc.models.port_hamiltonian import PortHamiltonian
from nsl_hpc.stacked import StackedModels
from tests.helpers import ARCH_NAMES

# Leading coefficient c of p ~ c n_d n_h^2 (unstructured: f at width 2 n_h, g at n_h).
LEADING_COEFFICIENT = {"unstructured": 5.0, "input_affine": 3.0, "port_hamiltonian": 4.0}
ARCH_CONFIGS = {"unstructured": {"name": "unstructured", "width_factor": 2.0},
                "input_affine": {"name": "input_affine"},
                "port_hamiltonian": {"name": "port_hamiltonian"}}


@pytest.mark.parametrize(("n", "m"), [(4, 2), (3, 1), (3, 2)])
@pytest.mark.parametrize("trial", range(5))
def test_port_hamiltonian_structure_holds_for_random_parameters(n, m, trial):
    torch.manual_seed(trial)
    model = PortHamiltonian(n, m, width=8, depth=2).double()
    for parameter in model.parameters():  # far from the initialisation too
        parameter.data.normal_(0, 3)
    z = torch.randn(64, n, dtype=torch.float64) * 5
    J, R, B = model.structure(z)
    torch.testing.assert_close(J, -J.transpose(1, 2), rtol=0, atol=0)
    torch.testing.assert_close(R, R.transpose(1, 2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(R).min() >= -1e-9 * R.abs().max()
    assert model.hamiltonian(z).min() >= 0
    assert B.shape == (64, n, m)


def test_port_hamiltonian_model_is_passive():
    """Along the model's own vector field dH/dt = -grad H^T R grad H + y^T v <= y^T v."""
    torch.manual_seed(0)
    model = PortHamiltonian(3, 2, width=8, depth=1).double()
    z, v = torch.randn(32, 3, dtype=torch.float64), torch.randn(32, 2, dtype=torch.float64)
    dz, y = model(z, v)
    grad = model.grad_hamiltonian(z)
    power = (grad * dz).sum(dim=1)
    assert torch.all(power <= (y * v).sum(dim=1) + 1e-12)


@pytest.mark.parametrize(("in_dim", "out_dim", "width", "depth"), [(3, 1, 1, 1), (6, 4, 7, 2), (4, 8, 32, 4)])
def test_mlp_parameter_count_closed_form(in_dim, out_dim, width, depth):
    assert parameter_count(mlp(in_dim, out_dim, width, depth)) == mlp_parameter_count(
        in_dim, out_dim, width, depth)


def expected_parameter_count(arch: str, n: int, m: int, width: int, depth: int) -> int:
    """The documented relation: the sum of the closed-form counts of each architecture's MLPs."""
    mlps = {
        "unstructured": [(n + m, n, 2 * width), (n, m, width)],
        "input_affine": [(n, n, width), (n, n * m, width), (n, m, width)],
        "port_hamiltonian": [(n, n * (n - 1) // 2, width), (n, n * (n + 1) // 2, width), (n, n * m, width),
                             (n, n, width)],
    }[arch]
    return sum(mlp_parameter_count(i, o, w, depth) for i, o, w in mlps)


@pytest.mark.parametrize("arch", sorted(ARCH_CONFIGS))
@pytest.mark.parametrize(("n", "m"), [(4, 2), (3, 1), (3, 2)])
@pytest.mark.parametrize(("width", "depth"), [(1, 1), (8, 2), (16, 4)])
def test_parameter_count_relation(arch, n, m, width, depth):
    p = parameter_count(build_model(ARCH_CONFIGS[arch], n, m, width=width, depth=depth))
    assert p == expected_parameter_count(arch, n, m, width, depth)


@pytest.mark.parametrize("arch", sorted(ARCH_CONFIGS))
def test_parameter_count_tends_to_c_nd_nh_squared(arch):
    """p / (n_d n_h^2) -> c (5, 3, 4): 4 n_d n_h^2 holds for wide models up to the factor c / 4."""
    for depth in (1, 2, 4):
        p = expected_parameter_count(arch, 4, 2, width=10_000, depth=depth)
        assert p / (depth * 10_000**2) == pytest.approx(LEADING_COEFFICIENT[arch], rel=1e-2)


@pytest.mark.parametrize("arch", sorted(ARCH_CONFIGS))
def test_forward_shapes(arch):
    model = build_model(ARCH_CONFIGS[arch], 4, 2, width=5, depth=1)
    dz, y = model(torch.randn(7, 4), torch.randn(7, 2))
    assert dz.shape == (7, 4) and y.shape == (7, 2)


def test_width_that_rounds_to_zero_is_refused():
    with pytest.raises(ConfigError, match=r"width_factor=0\.2"):
        build_model({"name": "unstructured", "width_factor": 0.2}, 4, 2, width=1, depth=1)


def test_unknown_architecture_is_refused():
    with pytest.raises(ConfigError, match="unknown arch 'narx'"):
        build_model({"name": "narx"}, 4, 2, width=4, depth=1)


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize(("state_dim", "input_dim"), [(4, 2), (3, 1)])
@pytest.mark.parametrize("count", [3, 24])  # 24 x 12 >= SPLIT_WIDTH: the unstructured f and g in two chains
def test_stacked_models_compute_what_each_model_computes(arch, state_dim, input_dim, count):
    """The fast path (the heads of K models, of widths 4-6 zero-padded, as batched MLPs, grad H written out)
    equals the modules, outputs and gradients, in float64."""
    torch.manual_seed(0)
    arch_cfg = OmegaConf.to_container(compose_config([f"arch={arch}"]).arch)
    models = [build_model(arch_cfg, state_dim, input_dim, width=4 + k % 3, depth=2).double() for k in range(count)]
    stack = StackedModels(models, torch.float64)
    z = torch.randn(count, 7, state_dim, dtype=torch.float64)
    v = torch.randn(count, 7, input_dim, dtype=torch.float64)
    dz, y = stack.forward(z, v)
    grad = stack.parameter_gradient(dz.square().sum() + y.square().sum())
    for k, model in enumerate(models):
        expected_dz, expected_y = model(z[k], v[k])
        torch.testing.assert_close(dz[k], expected_dz, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(y[k], expected_y, rtol=1e-12, atol=1e-12)
        grads = torch.autograd.grad(expected_dz.square().sum() + expected_y.square().sum(), list(model.parameters()))
        norm = torch.cat([g.flatten() for g in grads]).norm()
        torch.testing.assert_close(grad[k].norm(), norm, rtol=1e-12, atol=1e-12)  # padding gets no gradient
