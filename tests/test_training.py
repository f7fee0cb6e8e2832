"""Training: schedule, batching, loss, and real learning of every architecture on every system."""

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nsl_hpc.datasets import build_test_set, build_training_set
from nsl_hpc.metrics import normalized_errors
from nsl_hpc.models import build_model
from nsl_hpc.systems import SYSTEMS
from nsl_hpc.training import (
    Scaling,
    batch_bounds,
    batch_count,
    batch_normalized_mse,
    predict_derivative,
    train_model,
    warmup_cosine,
)
from tests.helpers import ARCH_NAMES, SYSTEM_NAMES

# A trained model must reach at most this fraction of an untrained model's nMAE. Measured with the
# settings below (2 trajectories, n_h = 16, n_d = 1, 60 epochs = 480 steps, default train config),
# trained / untrained nMAE: spring 0.11-0.19, ball 0.32-0.44, motor 0.47-0.62 (untrained: 0.69-1.01).
LEARNING_MARGIN = 0.7


def test_warmup_then_cosine_to_zero():
    lr = warmup_cosine(total_steps=1000, warmup_fraction=0.1, lr=1e-3)
    assert lr[0] == pytest.approx(1e-5) and lr[99] == pytest.approx(1e-3)
    assert np.all(np.diff(lr[:100]) > 0) and np.all(np.diff(lr[100:]) <= 0)
    assert lr[550] == pytest.approx(0.5e-3, rel=0.01) and lr[-1] < 1e-8


@pytest.mark.parametrize(("samples", "expected"), [
    (100, [(0, 100)]), (512, [(0, 256), (256, 512)]), (513, [(0, 256), (256, 513)]),
    (600, [(0, 256), (256, 512), (512, 600)]), (257, [(0, 257)]),
])
def test_batch_bounds(samples, expected):
    assert batch_bounds(samples, 256) == expected
    assert batch_count(samples, 256) == len(expected)


def test_batch_normalized_mse_divides_by_batch_spread():
    target = torch.tensor([[0.0, 0.0], [2.0, 20.0]])  # spreads (ddof 0): 1 and 10
    predicted = target + torch.tensor([[1.0, 10.0], [1.0, 10.0]])
    assert batch_normalized_mse(predicted, target, floor=1e-6).item() == pytest.approx(1.0)


@pytest.mark.parametrize("system", SYSTEM_NAMES)
@pytest.mark.parametrize("arch", ARCH_NAMES)
def test_short_training_beats_untrained_model(system, arch, compose, cache):
    cfg = compose(f"system={system}", f"arch={arch}")
    system_cfg = OmegaConf.to_container(cfg.system, resolve=True)
    train = build_training_set(system_cfg, 0, 2.0, cache)
    test = build_test_set(system_cfg, cache)
    torch.manual_seed(0)
    model = build_model(cfg.arch, SYSTEMS[system].state_dim, SYSTEMS[system].input_dim, width=16, depth=1)
    scaling = Scaling.fit(train)
    untrained = normalized_errors(test.dx, predict_derivative(model, test, scaling, torch.float32))["nmae"]
    outcome = train_model(model, train, scaling, cfg.train, epochs=60, shuffle_seed=0)
    trained = normalized_errors(test.dx, predict_derivative(model, test, scaling, torch.float32))["nmae"]
    assert outcome.finite and outcome.steps == 60 * 8
    assert trained < LEARNING_MARGIN * untrained, f"{system}/{arch}: {trained:.3f} vs {untrained:.3f}"
