"""Disagreement: the variance of an ensemble of forward models as the reward
(docs/methods.md, "Disagreement").

K forward models ``f_k(s, a) = Linear(s+a -> H) -> ReLU -> Linear(H -> s)`` predict the agent's
successor state ``s'`` (``batch.next_obs``). Each update first trains them on the mean L2 error
``||s' - f_k(s, a)||`` (the norm, not its square), then scores every row with the updated models:
``r = mean over state dims of the unbiased variance across the K predictions``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import TwinHead, call_network
from dvfb.nets.members import member_mean
from dvfb.rewards.base import IntrinsicReward, Runner


@dataclass
class DisagreementConfig:
    """Disagreement's ensemble (URLB defaults)."""

    ensemble_size: int = param(5, "Number K of forward models in the ensemble.", at_least=2)
    hidden_dim: int = param(1024, "Hidden width H of every forward model.", at_least=1)
    lr: float = param(1e-4, "Adam learning rate of the ensemble.", above=0)


class DisagreementReward(IntrinsicReward):
    """Ensemble of forward models; reward = their disagreement on ``(s, a)``."""

    def __init__(self, obs_dim: int, action_dim: int, config: DisagreementConfig | None = None):
        super().__init__()
        self.config = config if config is not None else DisagreementConfig()
        if self.config.ensemble_size < 2:
            raise ConfigError("disagreement needs an ensemble of at least 2 models "
                              f"(the variance across 1 is undefined), got {self.config.ensemble_size}")
        # One TwinHead is the K models as one wide and one batched product. URLB's ensemble keeps
        # PyTorch's default Linear init (no orthogonal init), hence init="default".
        self.ensemble = TwinHead(obs_dim + action_dim, self.config.hidden_dim, obs_dim,
                                 self.config.ensemble_size, init="default")

    def predict(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Every model's prediction of ``s'`` from ``(s, a)``: ``(K, N, obs_dim)`` (a group's ``(M, K, N, obs_dim)``)."""
        return run(self.ensemble, torch.cat([batch.obs, batch.action], dim=-1))

    def loss(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Mean over rows and models of ``||s' - f_k(s, a)||_2``."""
        error = batch.next_obs.unsqueeze(-3) - self.predict(batch, run)
        return member_mean(error.norm(dim=-1), self.members)

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        loss = self.loss(batch, run)
        self.step(loss)
        return {"disagreement_loss": loss.detach()}

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        # The update's predictions are stale after the step, so the score runs the models again
        # (hence no update_and_score override).
        prediction = self.predict(batch, run)
        return prediction.var(dim=-3, unbiased=True).mean(dim=-1, keepdim=True)
