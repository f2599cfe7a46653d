"""DIAYN: a skill discriminator on the n-step successor state (docs/methods.md, "DIAYN").

A discriminator ``q(z|s) = MLP(O -> H -> H -> d)`` (ReLU, logits) is trained with the cross-entropy
of the one-hot skill index on ``s' = batch.next_obs`` (``s_{t+3}`` for the URLB-style agents).
After that step the reward of every row, with the updated discriminator, is

    r = scale * (log softmax(q(s'))[z] - log(1/d)) = scale * (log q(z|s') + log d),

which is 0 when the discriminator is no better than the uniform prior over the d skills.
All layers use orthogonal init with zero biases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import call_network, mlp, orthogonal_init_
from dvfb.nets.members import member_mean
from dvfb.nets.skills import skill_index
from dvfb.rewards.base import IntrinsicReward, Runner


@dataclass
class DIAYNConfig:
    """DIAYN's skill and discriminator (URLB ``diayn`` defaults)."""

    skill_dim: int = param(16, "Number d of discrete skills (one-hot width).", at_least=2)
    skill_every: int = param(50, "Resample the rollout skill when the step counter is a multiple of this "
                             "(and at every episode start).", at_least=1)
    hidden_dim: int = param(1024, "Hidden width of the discriminator q(z|s).", at_least=1)
    scale: float = param(1.0, "Multiplier of the reward log q(z|s') + log d.", at_least=0)
    lr: float = param(1e-4, "Adam learning rate of the discriminator.", above=0)


def rowwise_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The cross-entropy of every row, ``target``'s shape: logits ``(..., N, d)``, target ``(..., N)``
    (a group's ``(M, N, d)`` member by member: F.cross_entropy wants the classes on dim 1)."""
    if logits.dim() == 2:
        return F_nn.cross_entropy(logits, target, reduction="none")
    # One call per member, on the ordinary shapes: it rounds as a separate run's.
    return torch.stack([rowwise_cross_entropy(logits[k], target[k]) for k in range(logits.shape[0])])


class DIAYNReward(IntrinsicReward):
    """Discriminator step on ``(s', z)``, then ``scale * (log q(z|s') + log d)``."""

    def __init__(self, obs_dim: int, skill_dim: int, config: DIAYNConfig | None = None):
        super().__init__()
        self.config = c = config if config is not None else DIAYNConfig()
        self.skill_dim = skill_dim
        self.discriminator = mlp(obs_dim, c.hidden_dim, c.hidden_dim, skill_dim)
        orthogonal_init_(self)

    def logits(self, obs: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        return run(self.discriminator, obs)

    def loss(self, batch: Batch, run: Runner = call_network) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean cross-entropy of the skill index on ``s'``, and the discriminator's accuracy."""
        logits = self.logits(batch.next_obs, run)
        target = skill_index(batch.z)
        accuracy = member_mean((logits.detach().argmax(dim=-1) == target).float(), self.members)
        if not self.members:
            return F_nn.cross_entropy(logits, target), accuracy
        # Each member's own mean-reduced cross-entropy: its gradient rounds as a separate run's.
        return torch.stack([F_nn.cross_entropy(logits[k], target[k]) for k in range(self.members)]), accuracy

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        loss, accuracy = self.loss(batch, run)
        self.step(loss)
        return {"diayn_loss": loss.detach(), "diayn_accuracy": accuracy}

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        # Recomputed after the step: URLB scores with the updated discriminator.
        log_q = F_nn.log_softmax(self.logits(batch.next_obs, run), dim=-1)
        log_q_z = log_q.gather(-1, skill_index(batch.z).unsqueeze(-1))  # (N, 1)
        return self.config.scale * (log_q_z + math.log(self.skill_dim))
