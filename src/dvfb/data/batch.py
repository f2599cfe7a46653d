"""A batch of transitions: what a replay or a dataset hands an update (docs/methods.md §6)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch


@dataclass
class Batch:
    """A batch of transitions, all tensors on the buffer's device.

    ``reward`` and ``discount`` have shape (B, 1); ``discount`` is ``gamma * env_discount`` for
    one-step batches, and ``gamma^n`` times the n environment discounts for n-step batches, whose
    ``next_obs`` is ``s_{t+n}`` and ``reward`` the discounted n-step sum (docs/methods.md §6).
    ``future_obs`` is ``obs_{t+2}`` when it was requested, else None.
    ``z`` is the stored rollout skill, (B, z_dim), or None when the buffer has no skill column.
    ``columns`` holds the other declared per-step columns of ``s_t``'s row by name (empty unless
    the buffer declares some, e.g. physics states for datasets); a column that goes with the
    observation (``Column(..., row="obs")``) also comes as ``next_<name>``, its value with
    ``next_obs``.
    """

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_obs: torch.Tensor
    future_obs: torch.Tensor | None
    z: torch.Tensor | None
    columns: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return self.obs.shape[-2]  # rows; a group's batch (docs/members.md) is (M, B, ...)

    def chunk(self, n: int) -> list[Batch]:
        """``n`` equal batches of the rows (the last may be shorter): a batch of ``n * B`` uniform
        draws is ``n`` independent batches of ``B`` (BeCL's fresh batch per contrastive step)."""
        size = -(-len(self) // n)

        def part(x: torch.Tensor | None, i: int) -> torch.Tensor | None:
            return None if x is None else x[..., i * size:(i + 1) * size, :]

        tensors = [f.name for f in dataclasses.fields(self) if f.name != "columns"]
        return [Batch(*(part(getattr(self, name), i) for name in tensors),
                      columns={k: part(v, i) for k, v in self.columns.items()}) for i in range(n)]

    @staticmethod
    def stack(batches: list[Batch]) -> Batch:
        """A group's batch (docs/members.md): member k's rows are ``batches[k]``, on a leading axis."""
        first = batches[0]

        def stacked(name: str) -> torch.Tensor | None:
            return None if getattr(first, name) is None else torch.stack([getattr(b, name) for b in batches])

        tensors = [f.name for f in dataclasses.fields(Batch) if f.name != "columns"]
        return Batch(*(stacked(name) for name in tensors),
                     columns={k: torch.stack([b.columns[k] for b in batches]) for k in first.columns})

    def to(self, device: str | torch.device) -> Batch:
        """The same batch with every tensor moved to ``device``."""

        def move(x: torch.Tensor | None) -> torch.Tensor | None:
            return None if x is None else x.to(device)

        return Batch(move(self.obs), move(self.action), move(self.reward), move(self.discount),
                     move(self.next_obs), move(self.future_obs), move(self.z),
                     {k: move(v) for k, v in self.columns.items()})
