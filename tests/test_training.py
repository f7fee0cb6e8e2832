"""Training: schedule, batching, loss, and real learning of every architecture on every system."""

import dataclasses
import tracemalloc

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch._dynamo.utils import counters

from nsl_hpc.config import config_dir
from nsl_hpc.config.schema import typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models import build_model
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_state.data import Dataset, build_test_set, build_training_set
from nsl_hpc.studies.input_state.lockstep import (
    BatchPlan,
    Member,
    loss_weights,
    predict_derivatives,
    score_derivatives,
    train_lockstep,
)
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.input_state.study import system_dimensions
from nsl_hpc.studies.metrics import normalized_errors
from nsl_hpc.studies.settings import InputStateTrain, batch_bounds, batch_count, warmup_cosine
from nsl_hpc.studies.training import Adam, StepCompiler, stack_rows
from tests.helpers import ARCH_NAMES, SYSTEM_NAMES, scores_both_ways

# A trained model must reach at most this fraction of an untrained model's nMAE. Measured with the
# settings below (4 trajectories, n_h = 16, n_d = 1, 50 epochs = 800 steps, the study's train config, seeds
# 0 and 1), trained / untrained nMAE: spring 0.17-0.42, ball 0.23-0.61, motor 0.64-0.69 (untrained: 0.70-1.11).
LEARNING_MARGIN = 0.8


def test_warmup_then_cosine_to_zero():
    """The authors' LambdaLR factor: s / (0.1 T), then (1 + cos(pi (s - 0.1 T) / (0.9 T))) / 2."""
    lr = warmup_cosine(total_steps=1000, warmup_fraction=0.1, lr=1e-3)
    assert lr[0] == 0 and lr[50] == pytest.approx(0.5e-3) and lr[100] == pytest.approx(1e-3)
    assert np.all(np.diff(lr[:101]) > 0) and np.all(np.diff(lr[100:]) < 0)
    assert lr[550] == pytest.approx(0.5e-3) and lr[-1] == pytest.approx(1e-3 * 0.5 * (1 + np.cos(np.pi * 899 / 900)))


@pytest.mark.parametrize(("samples", "expected"), [
    (100, [(0, 100)]), (512, [(0, 256), (256, 512)]), (513, [(0, 256), (256, 513)]),
    (600, [(0, 256), (256, 512), (512, 600)]), (257, [(0, 257)]),
])
def test_batch_bounds(samples, expected):
    assert batch_bounds(samples, 256) == expected
    assert batch_count(samples, 256) == len(expected)


def test_per_column_loss_divides_by_the_spread_of_each_column_of_the_unmasked_batch():
    """Columns: two states, one output (weight 0.25). Unmasked spreads (ddof 0): 1, 10 and 2; the errors are
    one spread each, so the loss is 1 (states) + 0.25 (output); a fully masked batch weighs nothing."""
    target = torch.tensor([[0.0, 0.0, 1.0], [2.0, 20.0, 5.0], [50.0, -7.0, 3.0]])
    predicted = target + torch.tensor([[1.0, 10.0, 2.0], [1.0, 10.0, 2.0], [99.0, 99.0, 99.0]])
    mask = torch.tensor([[1.0], [1.0], [0.0]])
    weights = loss_weights(target.T, mask.T, outputs=1, loss="per_column", output_weight=0.25, eps=1e-6)
    assert ((predicted - target).T * weights).square().sum().item() == pytest.approx(1.25)
    assert not loss_weights(target.T, torch.zeros(1, 3), 1, "per_column", 0.25, 1e-6).any()


def authors_normalized_mse(x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """utils.normalized_mse of the authors' code: one scalar std (ddof 1) of the whole target tensor."""
    return ((x - target) / (target.std() + 1e-6)).pow(2).mean()


def test_normalised_mse_divides_by_one_std_of_the_whole_target_of_the_unmasked_batch():
    """Hand-made batch of 4 samples (the last one padding): 2 states, 1 output. The dx/dt target
    [[0, 0], [3, 6], [6, 3]] has mean 3 and std sqrt(36 / 5); errors of 1 give 1 / 7.2 for the states; the
    output [1, 2, 6] has std sqrt(14 / 2), errors of 2 give 0.25 x 4 / 7."""
    target = torch.tensor([[0.0, 0.0, 1.0], [3.0, 6.0, 2.0], [6.0, 3.0, 6.0], [40.0, 40.0, 40.0]], dtype=torch.float64)
    predicted = target + torch.tensor([[1.0, -1.0, 2.0], [1.0, 1.0, -2.0], [-1.0, 1.0, 2.0], [9.0, 9.0, 9.0]],
                                      dtype=torch.float64)
    mask = torch.tensor([[1.0], [1.0], [1.0], [0.0]], dtype=torch.float64)
    weights = loss_weights(target.T, mask.T, outputs=1, loss="normalised_mse", output_weight=0.25, eps=1e-6)
    loss = ((predicted - target).T * weights).square().sum().item()
    assert loss == pytest.approx(1 / 7.2 + 0.25 * 4 / 7, rel=1e-6)
    expected = (authors_normalized_mse(predicted[:3, :2], target[:3, :2])
                + 0.25 * authors_normalized_mse(predicted[:3, 2:], target[:3, 2:]))
    assert loss == pytest.approx(expected.item(), rel=1e-12)


@pytest.mark.parametrize("system", SYSTEM_NAMES)
@pytest.mark.parametrize("arch", ARCH_NAMES)
def test_short_training_beats_untrained_model(system, arch, compose, cache):
    cfg = compose(f"system={system}", f"arch={arch}")
    system_cfg = pair_of(cfg).system
    train = build_training_set(system_cfg, 0, 4.0, cache)
    test = build_test_set(system_cfg, cache)
    torch.manual_seed(0)
    model = build_model(pair_of(cfg).arch, *system_dimensions(system_cfg), width=16, depth=1)
    member = Member(model, train, Scaling.fit(train, rescale_targets=False), epochs=50, shuffle_seed=0)
    untrained_stack, _ = train_lockstep([Member(model, train, member.scaling, 0, 0)], pair_of(cfg).train)
    untrained = normalized_errors(test.dx, *predict_derivatives(untrained_stack, test, [member.scaling],
                                                                torch.float32))["nmae"]
    stack, ((*_, last),) = train_lockstep([member], pair_of(cfg).train)
    outcome = last.outcome
    trained = normalized_errors(test.dx, *predict_derivatives(stack, test, [member.scaling], torch.float32))["nmae"]
    assert outcome.finite and outcome.steps == 50 * 16
    assert trained < LEARNING_MARGIN * untrained, f"{system}/{arch}: {trained:.3f} vs {untrained:.3f}"


# Packed training is the single-model loop per model: the final loss and metrics of a model trained with
# others of other widths, data sizes and epoch counts agree with it trained alone to this relative tolerance
# (float32; the batched operations sum in another order). Measured: 1e-6 and below.
PACKED_RTOL = 1e-4


@pytest.mark.parametrize("arch", ARCH_NAMES)
def test_a_model_trained_in_a_pack_matches_it_trained_alone(arch, compose, cache):
    cfg = compose("system=spring", f"arch={arch}")
    system_cfg = pair_of(cfg).system
    test = build_test_set(system_cfg, cache)
    members = []
    for seed, (n_traj, epochs, width) in enumerate([(0.7, 7, 6), (1.3, 4, 3), (2.05, 6, 6)]):
        data = build_training_set(system_cfg, seed, n_traj, cache)
        torch.manual_seed(seed)
        model = build_model(pair_of(cfg).arch, 4, 2, width=width, depth=2)  # the narrower one is zero-padded
        members.append(Member(model, data, Scaling.fit(data, rescale_targets=False), epochs, shuffle_seed=10 + seed))
    stack, snapshots = train_lockstep(members, pair_of(cfg).train)
    assert stack.count == 1  # the models that finished sooner left the stack
    outcomes = [member_snapshots[-1].outcome for member_snapshots in snapshots]
    packed = predict_derivatives(stack, test, [m.scaling for m in members], torch.float32,
                                 torch.stack([member_snapshots[-1].theta for member_snapshots in snapshots]),
                                 range(len(members)))
    for member, outcome, predicted in zip(members, outcomes, packed, strict=True):
        alone, ((*_, last),) = train_lockstep([member], pair_of(cfg).train)
        single = last.outcome
        assert outcome.steps == single.steps == member.epochs * batch_count(len(member.data), 256)
        assert outcome.final_loss == pytest.approx(single.final_loss, rel=PACKED_RTOL)
        expected = normalized_errors(test.dx, *predict_derivatives(alone, test, [member.scaling], torch.float32))
        assert normalized_errors(test.dx, predicted) == pytest.approx(expected, rel=PACKED_RTOL)


def compiled_members(cfg, cache, epochs: list[int]) -> list[Member]:
    """Spring models of widths 6, 3, 6, ... (the narrow ones zero-padded), n_d 1, 1.3 trajectories each."""
    system_cfg = pair_of(cfg).system
    members = []
    for seed, count in enumerate(epochs):
        data = build_training_set(system_cfg, seed, 1.3, cache)
        torch.manual_seed(seed)
        model = build_model(pair_of(cfg).arch, 4, 2, width=3 if seed % 2 else 6, depth=1)
        members.append(Member(model, data, Scaling.fit(data, rescale_targets=False), count, shuffle_seed=10 + seed))
    return members


def prediction(stack, snapshot, k: int, member: Member) -> np.ndarray:
    """dx/dt (N, n) on the member's training data of model k of ``stack`` with the parameters of ``snapshot``."""
    (predicted,) = predict_derivatives(stack, member.data, [member.scaling], torch.float32, snapshot.theta[None], [k])
    return predicted


def assert_trained_alike(one, other, members: list[Member], models: list[int]) -> None:
    """Two trainings (stack, snapshots) of ``members`` (model ``models[i]`` of ``one``, i of ``other``) agree to
    float rounding: steps, final losses and predictions after the last epoch."""
    for i, (k, member) in enumerate(zip(models, members, strict=True)):
        (*_, a), (*_, b) = one[1][k], other[1][i]
        assert a.outcome.steps == b.outcome.steps
        assert a.outcome.final_loss == pytest.approx(b.outcome.final_loss, rel=PACKED_RTOL)
        expected = prediction(other[0], b, i, member)
        np.testing.assert_allclose(prediction(one[0], a, k, member), expected, rtol=PACKED_RTOL,
                                   atol=PACKED_RTOL * np.abs(expected).max())


@pytest.mark.slow
def test_a_compiled_pack_trains_each_model_as_the_eager_loop_alone(compose, cache):
    """The compiled step (torch.compile, the pH energy gradient included) of a pack of two port-Hamiltonian models of
    different widths: each model's loss and predictions agree with it trained alone eagerly, to float rounding
    (unstructured: the next test, against the eager pack, which trains each model as alone: the test above;
    input-affine: compiled in a sweep, tests/test_clean.py)."""
    cfg = compose("system=spring", "arch=port_hamiltonian")
    members = compiled_members(cfg, cache, [3, 3])
    compiler = StepCompiler(True)
    counters.clear()
    packed = train_lockstep(members, pair_of(cfg).train, compiler=compiler)
    assert compiler.enabled
    assert counters["stats"]["unique_graphs"] == 1  # one shape, compiled once (no guard the first call fails)
    for k, member in enumerate(members):
        assert_trained_alike(packed, train_lockstep([member], pair_of(cfg).train), [member], [k])


@pytest.mark.slow
def test_a_compiled_pack_keeps_static_shapes_as_models_finish(compose, cache):
    """Four models of 100, 70, 50 and 20 steps (blocks of 32), compiled: the stack keeps its 4 rows after the
    first block (the finished model stays, padding only: 3 rows would be a new shape), 2 after the second, 1
    after the third; every model ends as the eager pack trains it."""
    cfg = compose("system=spring", "arch=unstructured")
    members = compiled_members(cfg, cache, [20, 14, 10, 4])  # 5 batches an epoch
    compiled = train_lockstep(members, pair_of(cfg).train, compiler=StepCompiler(True))
    assert compiled[0].count == 1
    assert_trained_alike(compiled, train_lockstep(members, pair_of(cfg).train), members, [0, 1, 2, 3])


def test_static_stacks_shrink_by_powers_of_two_topped_up_with_finished_rows():
    assert stack_rows([0, 4], 6, static=False) == [0, 4]
    assert stack_rows([0, 4, 5], 6, static=True) == [0, 1, 4, 5]  # 3 still training of 6 rows: 4 rows
    assert stack_rows([1, 2, 3, 5], 6, static=True) == [1, 2, 3, 5]
    assert stack_rows([0, 4], 6, static=True) == [0, 4]
    assert stack_rows([0, 1, 2, 3, 4], 6, static=True) == [0, 1, 2, 3, 4, 5]  # 8 >= 6: all stay
    assert stack_rows([3], 4, static=True) == [3]


def test_a_repeated_pass_takes_every_sample_repeat_times_in_batches_of_the_concatenation():
    """The authors' --repeat R: one epoch is one shuffled pass over the training set concatenated R times."""
    plan = BatchPlan(10, 8, epochs=2, seed=0, width=8, pad=99, repeat=3)
    assert plan.steps == 2 * 4  # ceil(30 / 8) batches per epoch
    batches = plan.next_pass()
    assert batches.shape == (4, 8)
    taken = batches[batches != 99]
    assert len(taken) == 30 and torch.equal(torch.bincount(taken, minlength=10), torch.full((10,), 3))
    assert (batches[-1] == 99).sum() == 2  # the last batch holds 6 samples, padded to the width


def milestone_run(compose, cache, schedule: str, epochs: int, milestones=(), schedule_epochs: int = 0,
                  overrides: tuple[str, ...] = ()):
    """Snapshots of one spring / input-affine model trained for ``epochs`` (1.3 trajectories: 1,300 samples, 6
    batches per epoch of one pass)."""
    cfg = compose("system=spring", "arch=input_affine", f"train.schedule={schedule}", *overrides)
    data = build_training_set(pair_of(cfg).system, 0, 1.3, cache)
    torch.manual_seed(0)
    model = build_model(pair_of(cfg).arch, 4, 2, width=6, depth=2)
    member = Member(model, data, Scaling.fit(data, rescale_targets=False), epochs, 7, milestones, schedule_epochs,
                    repeat=cfg.train.repeat)
    return train_lockstep([member], pair_of(cfg).train)[1][0]


@pytest.mark.parametrize(("clip", "decay", "reference"), [(0.0, 0.0, torch.optim.Adam),
                                                          (0.0, 0.01, torch.optim.AdamW)])
def test_the_stacked_optimizer_steps_each_row_as_torch_does(clip, decay, reference):
    """Without clipping, the stacked Adam (weight_decay 0) and AdamW step each row of theta as torch.optim's
    Adam and AdamW step that row alone, at each row's own learning rate."""
    torch.manual_seed(0)
    theta, grads = torch.randn(3, 5, dtype=torch.float64), torch.randn(4, 3, 5, dtype=torch.float64)
    rates = torch.tensor([[1e-2], [3e-3], [5e-2]], dtype=torch.float64)
    stacked = Adam(theta.clone(), clip, decay)
    for grad in grads:
        stacked.step(grad.clone(), rates)
    for k in range(3):
        row = theta[k].clone().requires_grad_()
        optimizer = reference([row], lr=float(rates[k]), weight_decay=decay)
        for grad in grads:
            row.grad = grad[k].clone()
            optimizer.step()
        torch.testing.assert_close(stacked.theta[k], row.detach(), rtol=1e-12, atol=1e-12)


def test_passes_by_trajectories_follow_the_last_pair_at_or_below_a_task():
    train = typed(InputStateTrain, {**OmegaConf.to_container(OmegaConf.load(config_dir() / "train" / "default.yaml")),
                                    "repeat_by_trajectories": [[1, 50], [3, 20], [10, 10], [30, 5]]}, "train")
    assert [train.passes(n_t) for n_t in (0.1, 1.0, 2.9, 3.0, 12.5, 51.2)] == [50, 50, 50, 20, 10, 5]
    assert dataclasses.replace(train, repeat_by_trajectories=None, repeat=4).passes(0.1) == 4
    for bad in ([[3, 20], [1, 50]], [[1, 2.5]], [[1]], [[]], [], [[1, 5], [1, 4]]):
        with pytest.raises(ConfigError, match="repeat_by_trajectories"):
            dataclasses.replace(train, repeat_by_trajectories=bad).check()
    with pytest.raises(ConfigError, match="both set"):
        dataclasses.replace(train, repeat=8).check()


def test_epoch_milestones_with_a_constant_learning_rate_are_the_separate_runs(compose, cache):
    snapshots = milestone_run(compose, cache, "constant", 6, milestones=(2, 4), schedule_epochs=6)
    assert [snapshot.epochs for snapshot in snapshots] == [2, 4, 6]
    for snapshot in snapshots:
        (alone,) = milestone_run(compose, cache, "constant", snapshot.epochs)
        assert snapshot.outcome.steps == alone.outcome.steps == snapshot.epochs * 6
        assert snapshot.outcome.final_loss == pytest.approx(alone.outcome.final_loss, rel=1e-6)
        torch.testing.assert_close(snapshot.theta, alone.theta, rtol=1e-6, atol=1e-7)


def test_an_epoch_over_repeated_data_takes_the_batches_of_the_repeated_set(compose, cache):
    (once,) = milestone_run(compose, cache, "constant", 2)
    (twice,) = milestone_run(compose, cache, "constant", 2, overrides=("train.repeat=2",))
    assert once.outcome.steps == 2 * 6 and twice.outcome.steps == 2 * 11  # 1,300 and 2,600 samples, batches of 256
    assert (once.theta - twice.theta).abs().max() > 1e-3


def test_epoch_milestones_with_warmup_cosine_follow_the_longer_schedule(compose, cache):
    """After 2 of 6 scheduled epochs the learning rate is still high: not the model of a 2-epoch schedule,
    which has decayed to 0 (docs/science.md, "Epoch milestones", measures the difference in the errors)."""
    first, _ = milestone_run(compose, cache, "warmup_cosine", 6, milestones=(2,), schedule_epochs=6)
    (alone,) = milestone_run(compose, cache, "warmup_cosine", 2)
    assert first.outcome.steps == alone.outcome.steps
    assert (first.theta - alone.theta).abs().max() > 1e-3


def test_a_diverging_model_leaves_the_others_of_its_pack_as_they_are_alone(compose, cache):
    """A model whose data hold a NaN diverges at its first batch (outcome not finite, snapshots of its later
    milestones not finite either); the other models of its pack train as they do alone."""
    cfg = compose("system=spring", "arch=port_hamiltonian")
    data = build_training_set(pair_of(cfg).system, 0, 1.3, cache)
    poisoned = dataclasses.replace(data, dx=np.where(np.arange(len(data))[:, None] == 5, np.nan, data.dx))

    def member(dataset, epochs, milestones=()):
        torch.manual_seed(0)
        model = build_model(pair_of(cfg).arch, 4, 2, width=4, depth=1)
        return Member(model, dataset, Scaling.fit(data, rescale_targets=False), epochs, 3, milestones)

    _, (bad, good) = train_lockstep([member(poisoned, 8, (2,)), member(data, 10)], pair_of(cfg).train)
    assert [snapshot.epochs for snapshot in bad] == [2, 8]
    assert all(not snapshot.outcome.finite and snapshot.outcome.steps <= 6 for snapshot in bad)
    _, (alone,) = train_lockstep([member(data, 10)], pair_of(cfg).train)
    assert good[-1].outcome.finite and good[-1].outcome.final_loss == pytest.approx(alone[-1].outcome.final_loss,
                                                                                    rel=PACKED_RTOL)


def test_a_group_scores_on_a_large_test_set_in_the_memory_of_a_chunk(compose, cache):
    """Scoring R models on N test samples holds one chunk of predictions, not R x N (a group of 32 on the
    200 x 200 s test set once reached 20 GB), and gives the scores of the whole predictions at once. NumPy's
    allocations are traced: the spreads of the test set take one temporary (N, n) array, whatever R."""
    cfg = compose("system=ball", "arch=input_affine")
    system_cfg = pair_of(cfg).system
    train = build_training_set(system_cfg, 0, 1.0, cache)
    rng = np.random.default_rng(0)
    samples = 100_000
    test = Dataset(*(rng.normal(size=(samples, columns)) for columns in (3, 1, 3, 1)))
    members = []
    for seed in range(8):
        torch.manual_seed(seed)
        model = build_model(pair_of(cfg).arch, 3, 1, width=8, depth=1)
        members.append(Member(model, train, Scaling.fit(train, rescale_targets=False), 0, seed))
    stack, _ = train_lockstep(members, pair_of(cfg).train)
    theta, models, scalings = stack.theta.detach(), range(len(members)), [m.scaling for m in members]
    one_model_bytes = samples * 3 * 8

    tracemalloc.start()
    scores = score_derivatives(stack, test, scalings, torch.float32, theta, models, "scalar")
    streamed_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    whole = predict_derivatives(stack, test, scalings, torch.float32, theta, models)
    whole_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()

    assert streamed_peak < 2 * one_model_bytes and len(members) * one_model_bytes <= whole_peak
    for model_scores, predicted in zip(scores, whole, strict=True):
        assert model_scores == pytest.approx(scores_both_ways(test.dx, predicted, "scalar"), rel=1e-12)
