"""Running statistics (docs/methods.md §3.4)."""

from __future__ import annotations

import torch
from torch import nn


class RunningMeanStd(nn.Module):
    """Scalar running mean and variance with the (0, 1, 1e-4) prior of §3.4.

    State lives in buffers on the module's device; :meth:`update` never syncs with the host.
    """

    def __init__(self, epsilon_count: float = 1e-4):
        super().__init__()
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var", torch.ones((), dtype=torch.float64))
        self.register_buffer("count", torch.full((), epsilon_count, dtype=torch.float64))

    members: int = 0  # a group (dvfb.nets.members): statistics (M,), one per member, of x (M, ...)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fold in a batch (Bessel-corrected batch variance) and return the new ``(mean, var)``."""
        x = x.detach().reshape(self.members, -1).double() if self.members else x.detach().reshape(-1).double()
        b = x.shape[-1]
        if self.members:  # each member's own reductions, rounding as its separate run's do
            batch_mean = torch.stack([row.mean() for row in x])
            batch_var = torch.stack([row.var(unbiased=True) for row in x]) if b > 1 else torch.zeros_like(batch_mean)
        else:
            batch_mean = x.mean()
            batch_var = x.var(unbiased=True) if b > 1 else torch.zeros_like(batch_mean)
        n = self.count
        total = n + b
        delta = batch_mean - self.mean
        self.mean.add_(delta * b / total)
        self.var.copy_((self.var * n + batch_var * b + delta.pow(2) * n * b / total) / total)
        self.count.add_(b)
        return self.mean, self.var
