"""Where the features of a batch lie, for the architectures' ``assemble``: last, (..., B, f) (batch-major: the
modules, the plain PyTorch form), or before the samples, (..., f, B) (feature-major: the stacked training path,
whose heads compute feature-major).

A matrix per sample is (..., B, r, c) batch-major and (..., r, c, B) feature-major. Feature-major, a product of
per-sample matrices is a few elementwise operations over rows of B contiguous samples instead of a batched
matmul of B K tiny matrices: for the 2-3 state matrices of the study, 4-5x faster at K = 32 and faster at K = 1
too (the pH and input-affine assemblies).
"""

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Layout:
    """Features last (batch-major) or, with ``feature_major``, before the samples."""

    feature_major: bool

    @property
    def axis(self) -> int:
        """The feature axis."""
        return -2 if self.feature_major else -1

    def take(self, x: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """Features start .. stop - 1 of ``x``."""
        return x.narrow(self.axis, start, stop - start)

    def matrix(self, x: torch.Tensor, rows: int, columns: int) -> torch.Tensor:
        """The rows x columns features of ``x`` (row-major) as a matrix per sample."""
        return x.unflatten(self.axis, (rows, columns))

    def column(self, x: torch.Tensor) -> torch.Tensor:
        """A vector of features per sample as a k x 1 matrix; ``vector`` undoes it."""
        return x.unsqueeze(self.axis)

    def vector(self, x: torch.Tensor) -> torch.Tensor:
        """A k x 1 matrix per sample as its k features."""
        return x.squeeze(self.axis)

    def transposed(self, x: torch.Tensor) -> torch.Tensor:
        """Each sample's matrix transposed."""
        return x.transpose(-3, -2) if self.feature_major else x.transpose(-1, -2)

    def matmul(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Each sample's matrix product a b: (r x k) (k x c) -> r x c."""
        if not self.feature_major:
            return a @ b
        return (a.unsqueeze(-2) * b.unsqueeze(-4)).sum(dim=-3)  # (..., r, k, c, B) summed over k

    def linear(self, x: torch.Tensor, mapping: torch.Tensor) -> torch.Tensor:
        """Features (..., k) mapped by ``mapping`` (k, f), the same for every sample: x mapping."""
        return mapping.T @ x if self.feature_major else x @ mapping


BATCH_MAJOR, FEATURE_MAJOR = Layout(False), Layout(True)
