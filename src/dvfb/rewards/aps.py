"""APS: successor-feature skills with a particle-entropy bonus (docs/methods.md, "APS").

A feature network ``phi(s) = MLP(O -> H -> H -> d)`` (ReLU) is read in two versions: raw, and
normalised ``phî = phi / ||phi||``. With the unit task ``w = batch.z`` and ``s' = batch.next_obs``
(``s_{t+3}`` for the URLB-style agents):

* loss (the von-Mises-Fisher log-likelihood of the direction): ``-mean_rows(w . phî(s'))``;
* reward, after that step and without gradient, with ``h = phi(s')`` raw:
  ``r = PBE-URLB(h) + w . h / ||h||``; PBE-URLB is the kNN particle entropy of ``h`` within the
  batch (k = 12, average, divided by the running mean of the distances, clip 1e-4, ``log(1+.)``).

:meth:`APSReward.regress_task` is URLB's fine-tuning task inference: the least-squares ``x`` of
``R x = Phî(s_t)`` (a 1 x d row regressed on the reward column), normalised to unit length.
All layers use orthogonal init with zero biases.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import call_network, mlp, orthogonal_init_
from dvfb.nets.members import member_mean
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.rewards.knn import KNNConfig, ParticleEntropy


@dataclass
class APSConfig:
    """APS's task, feature network and kNN estimator (URLB ``aps`` defaults)."""

    skill_dim: int = param(10, "Width d of the unit task vector w and of the features phi (sf_dim).", at_least=1)
    skill_every: int = param(5, "Resample the rollout task when the step counter is a multiple of this "
                             "(and at every episode start).", at_least=1)
    hidden_dim: int = param(1024, "Hidden width of the feature network phi.", at_least=1)
    knn_k: int = param(12, "Neighbours k of the particle-entropy reward (self included).", at_least=1)
    knn_average: bool = param(True, "Average over the k nearest distances (false: the k-th only).")
    knn_rms: bool = param(True, "Divide the kNN distances by their running mean (PBE-URLB's rms).")
    knn_clip: float = param(1e-4, "Clip subtracted from the (normalised) kNN distances (negative: none).")
    lr: float = param(1e-4, "Adam learning rate of the feature network.", above=0)

    def knn(self) -> KNNConfig:
        return KNNConfig(k=self.knn_k, average=self.knn_average, clip=self.knn_clip,
                         normaliser="mean" if self.knn_rms else "none")


class APSReward(IntrinsicReward):
    """Feature step on ``-w . phî(s')``, then ``PBE(phi(s')) + w . phî(s')``."""

    def __init__(self, obs_dim: int, skill_dim: int, config: APSConfig | None = None):
        super().__init__()
        self.config = c = config if config is not None else APSConfig()
        self.features = mlp(obs_dim, c.hidden_dim, c.hidden_dim, skill_dim)
        orthogonal_init_(self)
        self.entropy = ParticleEntropy(c.knn())  # its running mean is saved with the module

    def phi(self, obs: torch.Tensor, run: Runner = call_network, normalise: bool = True) -> torch.Tensor:
        """``phi(obs)``, normalised to unit rows unless ``normalise=False``."""
        feature = run(self.features, obs)
        return F_nn.normalize(feature, dim=-1) if normalise else feature

    def loss(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return -member_mean((batch.z * self.phi(batch.next_obs, run)).sum(dim=-1), self.members)

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        loss = self.loss(batch, run)
        self.step(loss)
        return {"aps_loss": loss.detach()}

    @torch.no_grad()
    def reward_parts(self, batch: Batch, run: Runner = call_network) -> tuple[torch.Tensor, torch.Tensor]:
        """The entropy and successor-feature parts of the reward, ``(N, 1)`` each. Folds the batch's
        kNN distances into the running mean."""
        raw = self.phi(batch.next_obs, run, normalise=False)
        entropy = self.entropy(raw)
        # F.normalize floors the norm at 1e-12 where URLB divides by the bare norm: equal for
        # every non-zero feature.
        sf = (batch.z * F_nn.normalize(raw, dim=-1)).sum(dim=-1, keepdim=True)
        return entropy, sf

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        entropy, sf = self.reward_parts(batch, run)
        return entropy + sf

    def update_and_score(self, batch: Batch, metrics: dict, run: Runner = call_network) -> torch.Tensor:
        metrics.update(self.update(batch, run))
        entropy, sf = self.reward_parts(batch, run)  # with the updated features, as URLB
        metrics.update(aps_entropy_reward=member_mean(entropy, self.members),
                       aps_sf_reward=member_mean(sf, self.members))
        return entropy + sf

    @torch.no_grad()
    def regress_task(self, obs: torch.Tensor, reward: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        """The unit task ``(d,)`` that best explains ``reward`` (URLB's fine-tuning regression).

        ``obs`` are states ``s_t`` ``(N, O)``, ``reward`` their n-step rewards ``(N, 1)`` or
        ``(N,)``. The least-squares row ``x`` of ``R x = Phî`` is ``R^T Phî / R^T R``; its direction,
        the one returned, is that of the reward-weighted feature sum ``sum_i R_i phî(s_i)``. An
        reward whose weighted sum has (numerically) no direction gives the zero vector, never a
        non-unit one (URLB would divide 0 by 0); without a host sync.
        """
        features = self.phi(obs, run)
        if self.members:  # (M, N, O) states: one task per member, (M, d)
            weighted = (reward.reshape(self.members, 1, -1).to(features.dtype) @ features).squeeze(-2)
            norm = weighted.norm(dim=-1, keepdim=True)
        else:
            weighted = (reward.reshape(1, -1).to(features.dtype) @ features)[0]  # (d,)
            norm = weighted.norm()
        return torch.where(norm > 1e-12, weighted / norm.clamp_min(1e-12), torch.zeros_like(weighted))
