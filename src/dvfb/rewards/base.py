"""The one small interface every intrinsic-reward module implements (docs/methods.md, "Rewards").

A reward module owns its networks, running statistics and optimiser. An agent calls it once per
update with the sampled :class:`~dvfb.data.Batch`:

* :meth:`IntrinsicReward.update` -- gradient step(s) of the module's own losses on the batch;
* :meth:`IntrinsicReward.score` -- the reward of every row, ``(N, 1)``, without gradient;
* :meth:`IntrinsicReward.update_and_score` -- both, in that order (every URLB-style module trains
  first and then scores with its updated networks). Modules override it when the score can reuse a
  forward pass of the update.

What a row's fields mean is the agent's business: for the URLB-style agents ``batch.next_obs`` is
the n-step successor ``s_{t+n}``; for DVFB it is ``s_{t+1}``. A module that pairs rows with skills
reads them with :meth:`IntrinsicReward.skills`: the stored skill ``batch.z``, or the column its
owner names in ``skill_column`` (DVFB's B labels, ``batch.columns["b_label"]``).

``run(net, *inputs)`` is how a module calls its networks: agents pass their
:class:`~dvfb.nets.execution.NetRunner` so that precision and compilation apply; the default calls
the network directly.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn

from dvfb.data import Batch
from dvfb.nets import adam, call_network
from dvfb.nets.members import minimise

Runner = Callable[..., torch.Tensor]


class IntrinsicReward(nn.Module):
    """Base class: update on a batch, score a batch. Subclasses implement :meth:`update` and
    :meth:`score`, and build ``self.optimizer`` in :meth:`make_optimizer` when they learn."""

    optimizer: torch.optim.Optimizer | None = None
    # The run's random stream for modules that draw (Proto's and CeSD's samples, SMM's noise);
    # None: torch's global one. Set by the owning agent (Agent.use_generator).
    generator: torch.Generator | None = None
    # Which batch column holds the skill each row is paired with: None for the stored skill
    # (batch.z); DVFB names the column of B's labels.
    skill_column: str | None = None
    # A group's member count (docs/members.md): set on every module by dvfb.nets.members.stack_agents.
    members: int = 0

    def skills(self, batch: Batch) -> torch.Tensor:
        """The skill of every row this module pairs the row with (see ``skill_column``)."""
        return batch.z if self.skill_column is None else batch.columns[self.skill_column]

    def make_optimizer(self, lr: float, fused: bool = True) -> None:
        """Create ``self.optimizer`` (Adam) over the module's trainable parameters; the agent calls
        this once after moving the module to its device."""
        params = [p for p in self.parameters() if p.requires_grad]
        self.optimizer = adam(params, lr, fused) if params else None

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        """Train the module on ``batch``; returns detached metric tensors (no host sync)."""
        return {}

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """The intrinsic reward of every row of ``batch``, ``(N, 1)``, without gradient."""
        raise NotImplementedError

    def update_and_score(self, batch: Batch, metrics: dict, run: Runner = call_network) -> torch.Tensor:
        metrics.update(self.update(batch, run))
        with torch.no_grad():
            return self.score(batch, run)

    def step(self, loss: torch.Tensor) -> None:
        """One optimiser step on ``loss`` (zero_grad, backward, step); a group's ``(M,)`` losses
        are each their member's (:func:`~dvfb.nets.members.minimise`)."""
        minimise(self.optimizer, loss)
