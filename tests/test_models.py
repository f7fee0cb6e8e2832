"""Architectures: the paper's equations, port-Hamiltonian structure for any parameters, parameter counts in
closed form, and the stacked path equal to the modules."""

import math

import pytest
import torch

from nsl_hpc.config import compose_config
from nsl_hpc.config.arch import Arch, arch_settings
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import mlp, parameter_count
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, FEATURE_MAJOR
from nsl_hpc.studies.input_state.stacked import StackedModels
from nsl_hpc.studies.input_state.study import system_dimensions
from tests.helpers import ARCH_NAMES, SYSTEM_NAMES, mlp_parameter_count, system_settings

# Variants of each architecture besides the study's (conf/arch): today's choices stay buildable.
VARIANTS = {
    "unstructured": [[], ["arch.form=split"], ["arch.block=tanh"]],
    "input_affine": [[], ["arch.feedthrough=true", "arch.width_factor=2.0"], ["arch.block=tanh"]],
    "port_hamiltonian": [[], ["arch.hamiltonian=plain"], ["arch.hamiltonian=half_square",
                                                          "arch.dissipation=lower_triangular", "arch.block=tanh"]],
}


def arch_config(arch: str, *overrides: str) -> Arch:
    """The typed ``arch`` group of ``arch`` with ``overrides``."""
    return arch_settings(compose_config([f"arch={arch}", *overrides]).arch)


def closed_form_count(in_dim: int, out_dim: int, w: int, n_d: int) -> int:
    """The issue's closed form of a Linear -> LayerNorm -> SiLU MLP: (in+1)w + 2w + (n_d-1)((w+1)w + 2w) + (w+1)out."""
    return (in_dim + 1) * w + 2 * w + (n_d - 1) * ((w + 1) * w + 2 * w) + (w + 1) * out_dim


def study_parameter_count(arch: str, n: int, m: int, n_h: int, n_d: int) -> int:
    """The study's architectures as the paper and the authors' code describe them, MLP by MLP."""
    mlps = {
        "unstructured": [(n + m, n + m, 2 * n_h)],  # one MLP of width 2 n_h from (x, u) to (dx/dt, y)
        "input_affine": [(n, n, n_h), (n, n * m, n_h), (n, m, n_h)],  # h, j, k
        "port_hamiltonian": [(n, n * (n - 1) // 2, n_h), (n, n * n, n_h), (n, n * m, n_h), (n, 1, n_h)],  # J R G H
    }[arch]
    return sum(closed_form_count(i, o, w, n_d) for i, o, w in mlps)


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("system", SYSTEM_NAMES)
@pytest.mark.parametrize(("n_h", "n_d"), [(1, 1), (5, 2), (16, 4)])
def test_parameter_count_is_the_closed_form(arch, system, n_h, n_d):
    n, m = system_dimensions(system_settings(system))
    model = build_model(arch_config(arch), n, m, width=n_h, depth=n_d)
    assert parameter_count(model) == study_parameter_count(arch, n, m, n_h, n_d)


@pytest.mark.parametrize(("in_dim", "out_dim", "width", "depth"), [(3, 1, 1, 1), (6, 4, 7, 2), (4, 8, 32, 4)])
@pytest.mark.parametrize("block", ["layernorm_silu", "tanh"])
def test_mlp_parameter_count_closed_form(in_dim, out_dim, width, depth, block):
    assert parameter_count(mlp(in_dim, out_dim, width, depth, block)) == mlp_parameter_count(
        in_dim, out_dim, width, depth, block)


def test_mlp_hidden_layers_are_linear_layernorm_silu():
    net = mlp(3, 2, width=5, depth=2, block="layernorm_silu")
    assert [type(layer).__name__ for layer in net] == ["Linear", "LayerNorm", "SiLU"] * 2 + ["Linear"]


def randomised(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """``model`` in float64 with parameters far from their initialisation (LayerNorm scales included)."""
    torch.manual_seed(seed)
    model = model.double()
    for parameter in model.parameters():
        parameter.data.normal_(0, 0.8)
    return model


@pytest.mark.parametrize(("n", "m"), [(4, 2), (3, 1), (3, 2)])
def test_modules_compute_the_papers_equations(n, m):
    """Each module against a plain re-implementation of (3a), (3b), (3c) from its MLPs' raw outputs."""
    z, v = torch.randn(9, n, dtype=torch.float64), torch.randn(9, m, dtype=torch.float64)

    unstructured = randomised(build_model(arch_config("unstructured"), n, m, 4, 2), 0)
    out = unstructured.nets["f"](torch.cat([z, v], dim=1))
    expected = (out[:, :n], out[:, n:])
    for got, want in zip(unstructured(z, v), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)

    affine = randomised(build_model(arch_config("input_affine"), n, m, 4, 2), 1)
    h, j, k = (affine.nets[name](z) for name in "hjk")
    dz = torch.stack([h[b] + j[b].reshape(n, m) @ v[b] for b in range(len(z))])
    torch.testing.assert_close(affine(z, v)[0], dz)
    torch.testing.assert_close(affine(z, v)[1], k)

    ph = randomised(build_model(arch_config("port_hamiltonian"), n, m, 4, 2), 2)
    raw_j, raw_q, raw_g = (ph.nets[name](z) for name in "JRG")
    zz = z.clone().requires_grad_(True)
    (grad_h,) = torch.autograd.grad(ph.nets["H"](zz).abs().sum(), zz)
    dz_rows, y_rows = [], []
    for b in range(len(z)):
        s = torch.zeros(n, n, dtype=torch.float64)
        entries = iter(raw_j[b])
        for row in range(n):
            for col in range(row + 1, n):
                s[row, col] = next(entries)
        q = raw_q[b].reshape(n, n)
        g = raw_g[b].reshape(n, m)
        dz_rows.append((s - s.T - q @ q.T / math.sqrt(n)) @ grad_h[b] + g @ v[b])
        y_rows.append(g.T @ grad_h[b])
    got_dz, got_y = ph(z, v)
    torch.testing.assert_close(got_dz, torch.stack(dz_rows))
    torch.testing.assert_close(got_y, torch.stack(y_rows))


@pytest.mark.parametrize("variant", range(3))
@pytest.mark.parametrize(("n", "m"), [(4, 2), (3, 1)])
def test_port_hamiltonian_structure_holds_for_random_parameters(variant, n, m):
    model = randomised(build_model(arch_config("port_hamiltonian", *VARIANTS["port_hamiltonian"][variant]),
                                   n, m, width=8, depth=2), variant)
    z = torch.randn(64, n, dtype=torch.float64) * 5
    outputs = {name: model.nets[name](z) for name in "JRG"}
    J, R, G = model.architecture.matrices(outputs)
    torch.testing.assert_close(J, -J.transpose(1, 2), rtol=0, atol=0)
    torch.testing.assert_close(R, R.transpose(1, 2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(R).min() >= -1e-9 * R.abs().max()
    assert G.shape == (64, n, m)
    if model.architecture.hamiltonian != "plain":
        assert model.architecture.energy(model.nets["H"](z)).min() >= 0


def test_port_hamiltonian_model_is_passive():
    """Along the model's own vector field dH/dt = -grad H^T R grad H + y^T v <= y^T v."""
    model = randomised(build_model(arch_config("port_hamiltonian"), 3, 2, width=8, depth=1), 0)
    z, v = torch.randn(32, 3, dtype=torch.float64), torch.randn(32, 2, dtype=torch.float64)
    dz, y = model(z, v)
    power = (model.grad_energy(z) * dz).sum(dim=1)
    assert torch.all(power <= (y * v).sum(dim=1) + 1e-12)


def test_width_that_rounds_to_zero_is_refused():
    with pytest.raises(ConfigError, match=r"arch\.width_factor=0\.2 gives"):
        build_model(arch_config("unstructured", "arch.width_factor=0.2"), 4, 2, width=1, depth=1)


@pytest.mark.parametrize(("override", "message"), [("arch.block=relu", "arch.block='relu' is unknown"),
                                                   ("arch.form=both", "arch.form='both' is unknown")])
def test_unknown_options_are_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        build_model(arch_config("unstructured", override), 4, 2, width=4, depth=1)


@pytest.mark.parametrize("arch", ARCH_NAMES)
@pytest.mark.parametrize("variant", range(3))
@pytest.mark.parametrize(("state_dim", "input_dim", "count"), [(4, 2, 1), (4, 2, 3), (3, 1, 24)])  # 24 x 12: 2 chains
def test_stacked_models_compute_what_each_model_computes(arch, variant, state_dim, input_dim, count):
    """The fast path (the heads of K models, of widths 4-6 zero-padded, as batched MLPs, grad H written out)
    equals the modules, outputs and parameter gradients, in float64."""
    arch_cfg = arch_config(arch, *VARIANTS[arch][variant])
    models = [randomised(build_model(arch_cfg, state_dim, input_dim, width=4 + k % 3, depth=2), k)
              for k in range(count)]
    stack = StackedModels(models, torch.float64)
    z = torch.randn(count, 7, state_dim, dtype=torch.float64)
    v = torch.randn(count, 7, input_dim, dtype=torch.float64)
    dz, y = stack.forward(torch.cat([z, v], dim=-1).transpose(1, 2))  # feature-major in and out
    grad = stack.parameter_gradient(dz.square().sum() + y.square().sum())
    for k, model in enumerate(models):
        expected_dz, expected_y = model(z[k], v[k])
        torch.testing.assert_close(dz[k].T, expected_dz, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(y[k].T, expected_y, rtol=1e-12, atol=1e-12)
        grads = torch.autograd.grad(expected_dz.square().sum() + expected_y.square().sum(), list(model.parameters()),
                                    materialize_grads=True)  # the H head's last bias does not enter grad H
        expected = torch.cat([g.flatten() for g in grads])
        torch.testing.assert_close(grad[k][grad[k] != 0].abs().sort().values,  # padding entries are exactly 0
                                   expected[expected != 0].abs().sort().values, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(("rows", "inner", "columns"), [(2, 2, 1), (3, 3, 3), (3, 2, 1)])
def test_feature_major_products_equal_the_batch_major_ones_sample_by_sample(rows, inner, columns):
    """Per-sample matrices as the stacked path holds them, (K, r, c, B), multiply, transpose and map as the
    modules' (K, B, r, c) do, to float64 rounding."""
    a = torch.randn(4, 9, rows * inner, dtype=torch.float64)  # (K, B, features) batch-major
    b = torch.randn(4, 9, inner * columns, dtype=torch.float64)
    mapping = torch.randn(rows * inner, 5, dtype=torch.float64)
    as_feature_major = lambda x: x.transpose(1, 2)  # noqa: E731
    batch = BATCH_MAJOR.matmul(BATCH_MAJOR.matrix(a, rows, inner), BATCH_MAJOR.matrix(b, inner, columns))
    feature = FEATURE_MAJOR.matmul(FEATURE_MAJOR.matrix(as_feature_major(a), rows, inner),
                                   FEATURE_MAJOR.matrix(as_feature_major(b), inner, columns))
    torch.testing.assert_close(feature.permute(0, 3, 1, 2), batch, rtol=1e-12, atol=1e-12)
    square = BATCH_MAJOR.matrix(a, rows, inner)
    torch.testing.assert_close(FEATURE_MAJOR.transposed(FEATURE_MAJOR.matrix(as_feature_major(a), rows, inner))
                               .permute(0, 3, 1, 2), BATCH_MAJOR.transposed(square))
    torch.testing.assert_close(FEATURE_MAJOR.linear(as_feature_major(a), mapping),
                               as_feature_major(BATCH_MAJOR.linear(a, mapping)), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(FEATURE_MAJOR.vector(FEATURE_MAJOR.column(as_feature_major(a))), as_feature_major(a))
    torch.testing.assert_close(FEATURE_MAJOR.take(as_feature_major(a), 1, 2), as_feature_major(a[..., 1:2]))
