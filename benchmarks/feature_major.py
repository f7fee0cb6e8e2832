"""Would a feature-major layout make the stacked MLPs' steps faster? (issue 31's remaining lever)

A lockstep chain's hidden layer holds its activations batch-major, (K, B, n_h): LayerNorm reduces over rows of
n_h = 2-64 contiguous values. Feature-major, (K, n_h, B), the same reduction runs over n_h rows of B = 256
contiguous values, which Inductor's loops (and ATen's elementwise kernels) vectorise. This times one training
step of a stacked chain (K MLPs of depth n_d with LayerNorm + SiLU, the study's block: forward, a mean square
loss, the parameters' gradients by autograd) in both layouts, eager and compiled, on one thread, and checks
that they compute the same gradients.

    .venv/bin/python benchmarks/feature_major.py [--shapes 2x1 8x2 16x4] [--models 32] [--repeats 5]
"""

import argparse
from collections.abc import Callable

import torch
from torch.nn import functional

from nsl_hpc.bench.measure import timed

EPS = 1e-5
BATCH, IN_DIM, OUT_DIM = 256, 3, 2  # spring: z, v in; dz/dt out


def parameters(models: int, width: int, depth: int, seed: int) -> list[torch.Tensor]:
    """Per hidden layer weight (K, in, n_h), bias, LayerNorm scale and shift (K, 1, n_h); then the output
    layer's weight (K, n_h, out) and bias (K, 1, out): the batch-major (current) layout."""
    generator = torch.Generator().manual_seed(seed)
    tensors = []
    for fan_in in [IN_DIM] + [width] * (depth - 1):
        tensors += [torch.randn(models, fan_in, width, generator=generator) / fan_in**0.5,
                    0.1 * torch.randn(models, 1, width, generator=generator),
                    1 + 0.1 * torch.randn(models, 1, width, generator=generator),
                    0.1 * torch.randn(models, 1, width, generator=generator)]
    return [*tensors, torch.randn(models, width, OUT_DIM, generator=generator) / width**0.5,
            0.1 * torch.randn(models, 1, OUT_DIM, generator=generator)]


def batch_major_loss(x: torch.Tensor, target: torch.Tensor, *tensors: torch.Tensor) -> torch.Tensor:
    """x (K, B, in), target (K, B, out): the mean square error of the chain, as the lockstep code computes it."""
    for weight, bias, scale, shift in zip(*[iter(tensors[:-2])] * 4, strict=True):
        a = torch.baddbmm(bias, x, weight)
        t = torch.addcmul(shift, functional.layer_norm(a, a.shape[-1:], eps=EPS), scale)
        x = functional.silu(t)
    return (torch.baddbmm(tensors[-1], x, tensors[-2]) - target).square().mean()


def feature_major_loss(x: torch.Tensor, target: torch.Tensor, *tensors: torch.Tensor) -> torch.Tensor:
    """The same chain with x (K, in, B), target (K, out, B) and every tensor transposed (its last two dims)."""
    for weight, bias, scale, shift in zip(*[iter(tensors[:-2])] * 4, strict=True):
        a = torch.baddbmm(bias, weight, x)  # (K, n_h, B)
        mean = a.mean(dim=1, keepdim=True)
        centered = a - mean
        normalized = centered * (centered.square().mean(dim=1, keepdim=True) + EPS).rsqrt()
        x = functional.silu(torch.addcmul(shift, normalized, scale))
    return (torch.baddbmm(tensors[-1], tensors[-2], x) - target).square().mean()


def gradient_step(loss: Callable[..., torch.Tensor]) -> Callable[..., list[torch.Tensor]]:
    def step(x: torch.Tensor, target: torch.Tensor, *tensors: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.autograd.grad(loss(x, target, *tensors), tensors))
    return step


def seconds_per_step(step: Callable[..., list[torch.Tensor]], args: list[torch.Tensor], repeats: int,
                     steps: int = 32) -> float:
    """The fastest of ``repeats`` blocks of ``steps`` calls, per call (s); one block first, untimed."""
    block = lambda: [step(*args) for _ in range(steps)]  # noqa: E731
    block()
    return min(timed(block)[1] for _ in range(repeats)) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["2x1", "8x2", "16x4"], help="n_h x n_d of the chain")
    parser.add_argument("--models", type=int, default=32, help="K, models in the stack")
    parser.add_argument("--repeats", type=int, default=5, help="timed blocks of 32 steps; the fastest counts")
    options = parser.parse_args()
    torch.set_num_threads(1)
    print(f"K = {options.models}, B = {BATCH}, one thread, torch {torch.__version__}; ms per step "
          f"(forward, loss, gradients), the fastest of {options.repeats} blocks of 32")
    print("| n_h x n_d | batch-major eager | feature-major eager | batch-major compiled | feature-major compiled "
          "| compiled ratio | max gradient difference |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for shape in options.shapes:
        width, depth = (int(part) for part in shape.split("x"))
        torch._dynamo.reset()  # each shape compiles afresh, not against the recompile limit
        tensors = [tensor.requires_grad_() for tensor in parameters(options.models, width, depth, 0)]
        transposed = [tensor.detach().transpose(1, 2).contiguous().requires_grad_() for tensor in tensors]
        generator = torch.Generator().manual_seed(1)
        x = torch.randn(options.models, BATCH, IN_DIM, generator=generator)
        target = torch.randn(options.models, BATCH, OUT_DIM, generator=generator)
        batch_args = [x, target, *tensors]
        feature_args = [x.transpose(1, 2).contiguous(), target.transpose(1, 2).contiguous(), *transposed]
        batch_step, feature_step = gradient_step(batch_major_loss), gradient_step(feature_major_loss)
        difference = max(float((g - h.transpose(1, 2)).abs().max() / g.abs().max().clamp_min(1e-12))
                         for g, h in zip(batch_step(*batch_args), feature_step(*feature_args), strict=True))
        times = [seconds_per_step(batch_step, batch_args, options.repeats),
                 seconds_per_step(feature_step, feature_args, options.repeats),
                 seconds_per_step(torch.compile(batch_step, dynamic=False), batch_args, options.repeats),
                 seconds_per_step(torch.compile(feature_step, dynamic=False), feature_args, options.repeats)]
        print(f"| {width} x {depth} | " + " | ".join(f"{1e3 * t:.2f}" for t in times)
              + f" | {times[2] / times[3]:.2f}x | {difference:.1e} |", flush=True)


if __name__ == "__main__":
    main()
