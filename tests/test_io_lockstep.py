"""The input-output fast path: NARX and SUBNET models trained packed equal the same models trained alone by
the plain loop (``train_io_model``), whatever their widths, training prefixes and iteration counts."""

import copy
import dataclasses

import numpy as np
import pytest
import torch

from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_output.data import Signals, load_benchmark
from nsl_hpc.studies.input_output.lockstep import IOMember, Windows, step_gradient, train_lockstep
from nsl_hpc.studies.input_output.stacked import StackedMLPs
from nsl_hpc.studies.input_output.study import build_io_model, horizon
from nsl_hpc.studies.input_output.training import SignalScaling, train_io_model
from nsl_hpc.studies.training import StepCompiler

# As for the input-state path (float32; batched operations sum in another order). Measured: 1e-7 and below.
# A model whose 150-step rollout is ill-conditioned at its initial weights (seen once: n_h 3, seed 1) has a
# float32 gradient that differs from its float64 one by its own size in either loop; the cases here are not.
PACKED_RTOL = 1e-4

# (prefix n_l, iterations, n_h, seed): every model has its own; n_l 300 and 400 give SUBNET fewer windows than
# a batch (B = W), 700 a pass of one batch of 256 (windows left over), 1300 several batches per pass.
MEMBERS = [(400, 7, 6, 0), (1300, 12, 3, 6), (300, 9, 5, 2), (700, 4, 6, 3)]


def members_of(cfg, cache, specs, record=None, steps=None) -> list[IOMember]:
    """Members of (n_l, iterations, n_h, seed) ``specs``, a SUBNET simulating ``steps`` per window (None: its horizon
    as a task's)."""
    pair = pair_of(cfg)
    train = load_benchmark(pair.system, cache).train if record is None else record
    members = []
    for points, iterations, width, seed in specs:
        torch.manual_seed(seed)
        model = build_io_model(pair.arch, pair.system, width, depth=2)
        prefix = train.head(points)
        own = horizon(pair, points)
        members.append(IOMember(model, prefix, SignalScaling.fit(prefix), iterations, 10 + seed,
                                steps if steps and cfg.arch.name == "subnet" else own))
    return members


def parameters_of(nets: StackedMLPs, theta: torch.Tensor, model: torch.nn.Module) -> list[torch.Tensor]:
    """The parameters of ``model``'s shape held in a row ``theta`` (1, P) of ``nets`` (padding cut off)."""
    alone = StackedMLPs([model], theta.dtype)
    cut = []
    for name, layers in alone.layers(alone.theta.detach()).items():
        for own, packed in zip(layers, nets.layers(theta)[name], strict=True):
            cut += [p[:, :o.shape[1], :o.shape[2]] for o, p in zip(own, packed, strict=True)]
    return cut


# SUBNET as deepSI lays it out: a bypass in every MLP, f without the residual, zero initial biases, n_x 10
DEEPSI = ("arch.bypass=[encoder,f,h]", "arch.residual=false", "arch.zero_bias=true", "arch.block=tanh",
          "arch.state_dim=10")
# NARX as deepSI lays it out: F an MLP plus a linear map of the regressors, tanh, zero initial biases
NARX_BYPASS = ("arch.bypass=true", "arch.zero_bias=true", "arch.block=tanh")
NARX_NO_BYPASS = ("arch.bypass=false", "arch.zero_bias=false", "arch.block=layernorm_silu")


@pytest.mark.parametrize(("arch", "compiled", "layout", "segment", "options"), [
    ("narx", False, "feature_major", 0, NARX_NO_BYPASS), ("subnet", False, "feature_major", 0, ()),
    ("narx", False, "batch_major", 0, NARX_NO_BYPASS), ("subnet", False, "batch_major", 0, ()),
    ("narx", False, "feature_major", 0, NARX_BYPASS), ("narx", False, "batch_major", 0, NARX_BYPASS),
    ("subnet", False, "feature_major", 0, DEEPSI), ("subnet", False, "batch_major", 0, DEEPSI),
    pytest.param("narx", True, "feature_major", 0, NARX_BYPASS, marks=pytest.mark.slow),
    pytest.param("subnet", True, "feature_major", 3, (), marks=pytest.mark.slow),
    pytest.param("subnet", True, "batch_major", 0, (), marks=pytest.mark.slow),
])
def test_models_trained_packed_equal_them_trained_alone_by_the_plain_loop(arch, compiled, layout, segment, options,
                                                                          compose, cache):
    """Eager, or compiled (``StepCompiler``, the first two models: one shape to compile; the compiled stack's
    shrinking is tests/test_checkpoints.py's), each model of the pack trains as the plain loop trains it alone,
    its activations stored either way (``train.feature_major_width``: the widths here are 3-6), NARX with and
    without its bypass, SUBNET in the paper's layout (bypass in h and the encoder, residual f) and in deepSI's
    (``DEEPSI``). Compiled SUBNET simulates T = 4 steps (Inductor takes a minute or more per shape to compile the
    study's segments), in one graph or recomputed in segments of 3 and 1 steps (``train.rollout_segment``)."""
    width = 8 if layout == "feature_major" else 0
    cfg = compose("study=input_output", "system=silverbox_sim", f"arch={arch}",
                  f"train.feature_major_width.{arch}={width}", f"train.rollout_segment.{layout}={segment}", *options)
    members = members_of(cfg, cache, MEMBERS[:2] if compiled else MEMBERS,  # compiled: 2 shapes to compile
                         steps=4 if compiled else None)
    assert_packed_equal_alone(members, cfg, compiled, layout)


def assert_packed_equal_alone(members, cfg, compiled=False, layout="batch_major"):
    """Each of ``members`` trained in lockstep ends where the plain loop takes it alone."""
    alone = [copy.deepcopy(member.model) for member in members]
    compiler = StepCompiler(compiled)
    nets, theta, outcomes = train_lockstep(members, pair_of(cfg).train, compiler=compiler)
    assert compiler.enabled == compiled and nets.feature_major == (layout == "feature_major")
    for k, (member, model) in enumerate(zip(members, alone, strict=True)):
        single = train_io_model(model, member.record, member.scaling, pair_of(cfg).train, member.iterations,
                                member.horizon, member.shuffle_seed)
        assert outcomes[k].steps == single.steps == member.iterations and outcomes[k].finite
        assert outcomes[k].final_loss == pytest.approx(single.final_loss, rel=PACKED_RTOL)
        trained_alone = StackedMLPs([model], torch.float32)
        for packed, own in zip(parameters_of(nets, theta[k:k + 1], model),
                               parameters_of(trained_alone, trained_alone.theta.detach(), model), strict=True):
            torch.testing.assert_close(packed, own, rtol=PACKED_RTOL, atol=1e-6)


@pytest.mark.parametrize("layout", ["feature_major", "batch_major"])
def test_a_prefix_shorter_than_one_window_trains_on_its_one_window_beside_full_windows(layout, compose, cache):
    """With ``arch.shorten_horizon`` a prefix of n_l < P + T samples has one window of n_l - P simulated steps
    (silverbox_sim: P 50, T 150; n_l 180 and 120: 130 and 70 steps); packed with a model of full windows, each
    trains as the plain loop trains it alone on its own horizon."""
    cfg = compose("study=input_output", "system=silverbox_sim", "arch=subnet",
                  f"train.feature_major_width.subnet={8 if layout == 'feature_major' else 0}")
    members = members_of(cfg, cache, [(180, 9, 5, 2), (700, 6, 6, 3), (120, 5, 4, 1)])
    assert [member.horizon for member in members] == [130, 150, 70]
    assert_packed_equal_alone(members, cfg, layout=layout)
    refused = compose("study=input_output", "system=silverbox_sim", "arch=subnet", "arch.shorten_horizon=false")
    assert horizon(pair_of(refused), 180) == 150


@pytest.mark.parametrize(("layout", "options", "horizons"), [
    ("feature_major", (), (7, 7, 7, 7)), ("batch_major", (), (7, 7, 7, 7)), ("batch_major", DEEPSI, (7, 7, 7, 7)),
    ("feature_major", (), (7, 5, 7, 2))])
def test_a_rollout_recomputed_in_segments_has_the_losses_and_gradient_of_the_whole_rollout(layout, options, horizons,
                                                                                           compose, cache):
    """``segmented_gradient`` (eager here: the function a compiled SUBNET step runs, its parts uncompiled) gives
    each model's loss and gradient as one backward through all T steps does, with segments that divide T or
    leave a shorter last one, and one longer than T; members of shorter horizons count only their own steps."""
    cfg = compose("study=input_output", "system=silverbox_sim", "arch=subnet", *options)
    members = [dataclasses.replace(member, horizon=steps)
               for member, steps in zip(members_of(cfg, cache, MEMBERS), horizons, strict=True)]
    windows = Windows(members, torch.float32)
    nets = StackedMLPs([member.model for member in members], torch.float32, 8 if layout == "feature_major" else 0)
    starts = torch.stack([torch.randperm(count, generator=torch.Generator().manual_seed(k))[:16]
                          for k, count in enumerate(windows.counts)])
    weights = torch.rand(len(members), 16, generator=torch.Generator().manual_seed(5))
    whole = step_gradient(windows, nets, StepCompiler(False), 0)(nets.theta, nets.gradient_mask, starts, weights)
    assert whole[1].abs().sum() > 0
    for segment in (1, 3, 7, 10):
        losses, grad = step_gradient(windows, nets, StepCompiler(False), segment)(nets.theta, nets.gradient_mask,
                                                                                 starts, weights)
        torch.testing.assert_close(losses, whole[0], rtol=1e-5, atol=0)
        # float32 sums in another order: entries far below the largest differ by more than their own 1e-4
        torch.testing.assert_close(grad, whole[1], rtol=1e-4, atol=1e-5 * float(whole[1].abs().max()))


@pytest.mark.parametrize(("arch", "options"), [("narx", NARX_NO_BYPASS), ("narx", NARX_BYPASS), ("subnet", ()),
                                               ("subnet", DEEPSI)])
def test_a_stack_laid_out_for_compiling_computes_the_losses_and_gradient_of_the_eager_stack(arch, options, compose,
                                                                                            cache):
    """A batch-major stack built for a compiled step (centred LayerNorm weights; its products of few output
    columns, f's and h's last layers or NARX's, computed as their transposes), here run eagerly, gives each
    model's loss and gradient as the eager stack does."""
    cfg = compose("study=input_output", "system=silverbox_sim", f"arch={arch}", *options)
    members = members_of(cfg, cache, MEMBERS, steps=7)
    windows = Windows(members, torch.float32)
    starts = torch.stack([torch.randperm(count, generator=torch.Generator().manual_seed(k))[:16]
                          for k, count in enumerate(windows.counts)])
    weights = torch.rand(len(members), 16, generator=torch.Generator().manual_seed(5))
    results = []
    for compiled in (False, True):
        nets = StackedMLPs([member.model for member in members], torch.float32, 0, compiled)
        assert not nets.feature_major and nets.centred == compiled
        results.append(step_gradient(windows, nets, StepCompiler(False), 0)(nets.theta, nets.gradient_mask, starts,
                                                                            weights))
    (losses, grad), (laid_out_losses, laid_out_grad) = results
    assert grad.abs().sum() > 0
    torch.testing.assert_close(laid_out_losses, losses, rtol=1e-5, atol=0)
    torch.testing.assert_close(laid_out_grad, grad, rtol=1e-4, atol=1e-5 * float(grad.abs().max()))


def test_a_diverging_model_leaves_the_others_of_its_pack_as_they_are_alone(compose, cache):
    """A NARX whose record holds a NaN has a NaN loss at the end of its first pass and stops there (as in the
    plain loop); the model packed with it trains as it does alone."""
    cfg = compose("study=input_output", "system=silverbox_sim", "arch=narx")
    train = load_benchmark(pair_of(cfg).system, cache).train.head(1300)
    poisoned = Signals(train.u, np.where(np.arange(len(train)) == 600, np.nan, train.y))
    bad = members_of(cfg, cache, [(1300, 20, 4, 0)], record=poisoned)[0]
    bad = dataclasses.replace(bad, scaling=SignalScaling.fit(train))
    good = members_of(cfg, cache, [(1300, 20, 6, 1)])[0]
    model = copy.deepcopy(good.model)
    _, _, (bad_outcome, good_outcome) = train_lockstep([bad, good], pair_of(cfg).train)
    per_pass = (1300 - 50) // 256
    assert not bad_outcome.finite and bad_outcome.steps == per_pass
    single = train_io_model(model, good.record, good.scaling, pair_of(cfg).train, 20, 1, good.shuffle_seed)
    assert good_outcome.finite and good_outcome.final_loss == pytest.approx(single.final_loss, rel=PACKED_RTOL)
