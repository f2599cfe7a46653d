"""The learner contract: what trains a model, in pre-training (a method's agent,
:class:`~dvfb.agents.base.Agent`) and in fine-tuning (a fine-tuner,
:class:`~dvfb.protocols.base.Finetuner`) (docs/architecture.md, "A method: model and learner").

Everything that trains calls a learner through these hooks and nothing else: a training loop's
group and its sessions (an update on a batch drawn by :meth:`Learner.replay_needs`, the batched
:meth:`Learner.act`, the hint of a non-finite loss), the resume checkpoints
(:meth:`Learner.training_state`, :meth:`Learner.load_training_state`) and the stacking of a
group's members (:mod:`dvfb.nets.members`: every tensor of the learner, its optimisers' states, its
random stream). A learner owns the model it trains (:attr:`Learner.model`); acting, the random
stream and how the networks execute are the model's, so the defaults here delegate to it.

It stands with the networks, below the agents and the protocols, because the member axis
(:mod:`dvfb.nets.members`) stacks learners of both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from dvfb.data import Batch


@dataclass(frozen=True)
class ReplayNeeds:
    """How a learner's batches are drawn from the replay buffer (docs/methods.md, "Replay").

    ``nstep``: rewards summed over n steps with ``discount = gamma^n`` and ``next_obs = s_{t+n}``,
    never across an episode boundary (n = 3 for the URLB-style agents). ``need_future``: the batch
    also carries ``s_{t+2}`` (FB's ``code_exact`` pairings).
    """

    batch_size: int
    discount: float
    nstep: int = 1
    need_future: bool = False

    def sample(self, replay, generator: torch.Generator | None = None) -> Batch:
        return replay.sample(self.batch_size, self.discount, need_future=self.need_future, nstep=self.nstep,
                             generator=generator)


class Learner(nn.Module):
    """Base class of everything that trains a model (see the module docstring). A subclass sets
    :attr:`model` and implements :meth:`replay_needs`, :meth:`update` and :meth:`optimizers`; the
    other hooks have defaults that fit a learner whose state is its modules and its optimisers."""

    # 0: one run; N: a group of N members on stacked tensors (docs/members.md).
    members: int = 0
    # The model it trains (a dvfb.agents.base.Model): its networks, skill, random stream and runner.
    model: Any

    # Acting and the random stream: the model's ---------------------------------------------------
    @property
    def generator(self) -> Any:
        """The run's random stream (a group's: one per member), the model's."""
        return self.model.generator

    @property
    def net_runner(self) -> Any:
        """How the networks execute (``--perf.*``), the model's."""
        return self.model.net_runner

    def use_generator(self, generator: Any) -> None:
        """Draw every random number of the learner, its modules and its model from ``generator``, the
        run's own stream, instead of torch's global one."""
        for module in self.modules():
            if module is not self and hasattr(module, "generator"):
                module.generator = generator
        self.model.use_generator(generator)

    def act(self, obs: np.ndarray, skills: torch.Tensor | None, explore: bool) -> np.ndarray:
        """Actions of a batch of observations (:meth:`dvfb.agents.base.Model.act`)."""
        return self.model.act(obs, skills, explore)

    def nonfinite_hint(self, metric_names: list[str]) -> str:
        """What to tell a user whose update produced these non-finite metrics ("" for nothing)."""
        return self.model.nonfinite_hint(metric_names)

    # Learning ------------------------------------------------------------------------------------
    def replay_needs(self) -> ReplayNeeds:
        """How the batches of :meth:`update` are drawn from the replay."""
        raise NotImplementedError

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One update on ``batch`` (a group's: its members' batches stacked); its metrics."""
        raise NotImplementedError

    # State ---------------------------------------------------------------------------------------
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """The optimisers by name (a group stacks their states)."""
        raise NotImplementedError

    def training_state(self) -> dict:
        """What a resume checkpoint keeps: the modules' tensors and the optimisers' states."""
        return {"modules": self.state_dict(),
                "optimizers": {name: optimizer.state_dict() for name, optimizer in self.optimizers().items()}}

    def load_training_state(self, state: dict) -> None:
        """Restore what :meth:`training_state` returned."""
        self.load_state_dict(state["modules"])
        for name, optimizer in self.optimizers().items():
            optimizer.load_state_dict(state["optimizers"][name])


__all__ = ["Learner", "ReplayNeeds"]
