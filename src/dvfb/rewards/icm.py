"""ICM-APT: an ICM-trained representation scored by particle entropy
(docs/methods.md, "ICM-APT").

A trunk ``e(s) = Tanh(LN(Linear(s -> rep)))`` is trained jointly with

* a forward model ``[e(s), a] -> H -> rep`` (ReLU) predicting ``e(s')``, and
* an inverse model ``[e(s), e(s')] -> H -> a`` (ReLU, output tanh) predicting ``a``,

on ``mean ||e(s') - fwd(e(s), a)|| + mean ||a - inv(e(s), e(s'))||`` (L2 norms, not squared;
``s' = batch.next_obs``, and the trunk gets gradient through both ``e(s)`` and ``e(s')``). After the
update the reward is the particle-entropy estimate over ``e(s)`` of the batch against itself
(docs/methods.md, "Rewards: kNN particle entropy"; k = 12, average, no running statistics, clip 0).
It scores the current state ``s``, not ``s'``. All layers use orthogonal init with zero biases.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import call_network, layernorm_tanh_layer, mlp, orthogonal_init_
from dvfb.nets.members import member_mean
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.rewards.knn import NORMALISERS, KNNConfig, ParticleEntropy


@dataclass
class ICMAPTConfig:
    """ICM-APT's networks and kNN estimator (URLB ``icm_apt`` defaults)."""

    rep_dim: int = param(512, "Width of the trunk's representation e(s).", at_least=1)
    hidden_dim: int = param(1024, "Hidden width of the forward and inverse models.", at_least=1)
    lr: float = param(1e-4, "Adam learning rate of trunk, forward and inverse model.", above=0)
    knn_k: int = param(12, "Neighbours k of the particle-entropy reward (self included).", at_least=1)
    knn_average: bool = param(True, "Average over the k nearest distances (false: the k-th only).")
    knn_clip: float = param(0.0, "Clip subtracted from the kNN distances (negative: none).")
    knn_normaliser: str = param("none", "Running normalisation of the kNN distances.", NORMALISERS)

    def knn(self) -> KNNConfig:
        return KNNConfig(k=self.knn_k, average=self.knn_average, clip=self.knn_clip,
                         normaliser=self.knn_normaliser)


class ICMAPTReward(IntrinsicReward):
    """ICM-trained trunk + kNN particle entropy of ``e(s)``."""

    def __init__(self, obs_dim: int, action_dim: int, config: ICMAPTConfig | None = None):
        super().__init__()
        self.config = c = config if config is not None else ICMAPTConfig()
        self.trunk = layernorm_tanh_layer(obs_dim, c.rep_dim)
        self.forward_model = mlp(c.rep_dim + action_dim, c.hidden_dim, c.rep_dim)
        self.inverse_model = mlp(2 * c.rep_dim, c.hidden_dim, action_dim, output_activation=nn.Tanh())
        orthogonal_init_(self)
        # Holds running statistics only when a normaliser is chosen (none by default).
        self.entropy = ParticleEntropy(c.knn())

    def loss(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Forward plus inverse L2 error, each averaged over the batch."""
        # One trunk pass over [s; s']: LayerNorm is per row, so this equals two separate passes.
        # Rows are dim -2 (after a group's member axis).
        rep_obs, rep_next = run(self.trunk, torch.cat([batch.obs, batch.next_obs], dim=-2)).chunk(2, dim=-2)
        next_hat = run(self.forward_model, torch.cat([rep_obs, batch.action], dim=-1))
        action_hat = run(self.inverse_model, torch.cat([rep_obs, rep_next], dim=-1))
        forward_error = (rep_next - next_hat).norm(dim=-1)
        inverse_error = (batch.action - action_hat).norm(dim=-1)
        return member_mean(forward_error, self.members) + member_mean(inverse_error, self.members)

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        loss = self.loss(batch, run)
        self.step(loss)
        return {"icm_loss": loss.detach()}

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        # The trunk changed in the update, so e(s) is recomputed here (no update_and_score override).
        return self.entropy(run(self.trunk, batch.obs))
