"""Contrastive skill/transition encoders and the rewards built on them (docs/methods.md, "Rewards").

* :func:`nce_loss` -- the CIC-style NCE loss of the encoders (§7.4);
* :func:`contrastive_entropy_reward` -- DVFB's kNN contrastive-entropy reward from one matrix
  product and a top-k, never an N x N x d tensor (§7.5, D7);
* :class:`ContrastiveEncoders` -- state encoder g, transition predictor and skill projector (§4.6);
* :class:`ContrastiveEntropyReward` -- DVFB's CE module: NCE step, then the CE reward;
* :class:`CICReward` -- CIC's module: NCE step, then the APT-CIC particle entropy of g(s').

Both modules read the skill of each row with ``self.skills(batch)``: the stored skill, or DVFB's
detached B labels (its ``skill_column``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import call_network, mlp, orthogonal_init_
from dvfb.nets.members import member_mean, row_products
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.rewards.knn import KNNConfig, ParticleEntropy

CE_NEIGHBOURS = ("least_similar", "most_similar")
CE_AGGREGATES = ("log_of_mean", "mean_of_log")


def nce_loss(query: torch.Tensor, key: torch.Tensor, temperature: float = 1.0,
             exact_positive: bool = False, members: int = 0) -> torch.Tensor:
    """Mean over rows of ``-log(exp(S_ii) / (neg_i + 1e-6))`` with ``S = q k^T / T`` (§7.4).

    ``neg_i = max(sum_j exp(S_ij) - e^{1/T}, 1e-6)``: the CIC trick removes the upper bound of the
    positive term. With ``exact_positive`` the exact ``exp(S_ii)`` is removed instead. A group's
    ``(M, N, c)`` inputs (``members = M``) give each member's own loss, ``(M,)``.
    """
    q = F_nn.normalize(query, dim=-1)
    k = F_nn.normalize(key, dim=-1)
    sim = row_products(q, k, members) / temperature
    exp_sim = sim.exp()
    positive = sim.diagonal(dim1=-2, dim2=-1)
    subtract = exp_sim.diagonal(dim1=-2, dim2=-1) if exact_positive else math.exp(1.0 / temperature)
    negative = (exp_sim.sum(-1) - subtract).clamp_min(1e-6)
    return member_mean(torch.log(negative + 1e-6) - positive, members)


def contrastive_entropy_reward(key: torch.Tensor, query: torch.Tensor, k: int = 12,
                               neighbours: str = "least_similar", aggregate: str = "log_of_mean",
                               temperature: float = 1.0) -> torch.Tensor:
    """CE reward ``(N, 1)`` of each transition key against the skill queries of all rows (§7.5).

    ``c_ij = cos(key_i, query_j)``; the k least (or most) similar ``j`` are kept, and the reward is
    ``log(1 + mean_j max(0, 1 - c_ij / T))`` (or the mean of the logs). Range ``[0, log 3]`` at T=1.
    """
    if neighbours not in CE_NEIGHBOURS:
        raise ValueError(f"ce_neighbours must be one of {CE_NEIGHBOURS}, got {neighbours!r}")
    if aggregate not in CE_AGGREGATES:
        raise ValueError(f"ce_aggregate must be one of {CE_AGGREGATES}, got {aggregate!r}")
    cos = F_nn.normalize(key, dim=-1) @ F_nn.normalize(query, dim=-1).mT  # (N, N)
    k = min(k, cos.shape[-1])
    nearest = cos.topk(k, dim=-1, largest=(neighbours == "most_similar")).values
    distance = (1.0 - nearest / temperature).clamp_min(0.0)
    if aggregate == "log_of_mean":
        return torch.log1p(distance.mean(-1, keepdim=True))
    return torch.log1p(distance).mean(-1, keepdim=True)


class ContrastiveEncoders(nn.Module):
    """The CIC-style encoders behind the CE reward (§4.6).

    * ``state_net`` g: ``O -> H -> H -> c``;
    * ``transition_net`` (pred): ``key(s, s') = pred([g(s), g(s')])``, ``2c -> H -> H -> c``;
    * ``skill_net`` (query): ``c -> H -> H -> c``.
    """

    def __init__(self, obs_dim: int, skill_dim: int, hidden_dim: int):
        super().__init__()
        self.state_net = mlp(obs_dim, hidden_dim, hidden_dim, skill_dim)
        self.transition_net = mlp(2 * skill_dim, hidden_dim, hidden_dim, skill_dim)
        self.skill_net = mlp(skill_dim, hidden_dim, hidden_dim, skill_dim)
        orthogonal_init_(self)

    def key(self, obs: torch.Tensor, next_obs: torch.Tensor, run=None) -> torch.Tensor:
        """``pred([g(s), g(s')])``; ``run(net, x)``, if given, calls the two networks."""
        run = run if run is not None else call_network
        # One pass of g over both columns instead of two (rows: dim -2, after a group's member axis).
        both = run(self.state_net, torch.cat([obs, next_obs], dim=-2))
        g_obs, g_next = both.chunk(2, dim=-2)
        return run(self.transition_net, torch.cat([g_obs, g_next], dim=-1))

    def query(self, skill: torch.Tensor) -> torch.Tensor:
        return self.skill_net(skill)


class ContrastiveEntropyReward(IntrinsicReward):
    """DVFB's contrastive-entropy module (§7.4, §7.5): an NCE step on (s, s', skill), then the CE
    reward of every transition key against the skill queries of the batch, with the updated
    encoders."""

    def __init__(self, obs_dim: int, skill_dim: int, hidden_dim: int, k: int = 12,
                 neighbours: str = "least_similar", aggregate: str = "log_of_mean", temperature: float = 1.0,
                 nce_temperature: float = 1.0, nce_exact_positive: bool = False):
        super().__init__()
        self.encoders = ContrastiveEncoders(obs_dim, skill_dim, hidden_dim)
        self.k, self.neighbours, self.aggregate, self.temperature = k, neighbours, aggregate, temperature
        self.nce_temperature, self.nce_exact_positive = nce_temperature, nce_exact_positive

    def _key_query(self, batch: Batch, run: Runner) -> tuple[torch.Tensor, torch.Tensor]:
        key = self.encoders.key(batch.obs, batch.next_obs, run)
        return key, run(self.encoders.skill_net, self.skills(batch))

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        key, query = self._key_query(batch, run)
        loss = nce_loss(query, key, self.nce_temperature, self.nce_exact_positive, self.members)
        self.step(loss)
        return {"nce_loss": loss.detach()}

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        key, query = self._key_query(batch, run)
        return contrastive_entropy_reward(key, query, self.k, self.neighbours, self.aggregate, self.temperature)


@dataclass
class CICConfig:
    """CIC's contrastive module and its APT reward (docs/methods.md, "CIC")."""

    hidden_dim: int = param(1024, "Hidden width of g, the transition predictor and the skill projector.", at_least=1)
    temperature: float = param(0.5, "Temperature T of the NCE loss.", above=0)
    knn_k: int = param(16, "Neighbours k of the APT particle-entropy reward.", at_least=1)
    knn_clip: float = param(0.0005, "Clip subtracted from the normalised kNN distances.", at_least=0)
    knn_rms: bool = param(True, "Divide the distances by the running variance (APT-CIC).")
    lr: float = param(1e-4, "Adam learning rate of the contrastive module.", above=0)


@dataclass
class CICSkillConfig(CICConfig):
    """CIC's skill and its contrastive module (the CIC and ComSD agents' section; DVFB(CIC) pairs the
    module with B's labels instead and has no skill settings)."""

    skill_dim: int = param(64, "Width of the skill, drawn from Uniform[0, 1]^d.", at_least=1)
    skill_every: int = param(50, "Resample the rollout skill when the step counter is a multiple of this (and at "
                             "every episode start).", at_least=1)


class CICReward(IntrinsicReward):
    """CIC (docs/methods.md, "CIC"): an NCE step, then ``log(1 + mean kNN distance)`` of g(s') within
    the batch, divided by the running variance of the distances (APT-CIC). The contrastive term
    only shapes g; it is not part of the reward (the released code's "og" reward)."""

    def __init__(self, obs_dim: int, skill_dim: int, config: CICConfig):
        super().__init__()
        self.config = config
        self.encoders = ContrastiveEncoders(obs_dim, skill_dim, config.hidden_dim)
        self.entropy = ParticleEntropy(KNNConfig(k=config.knn_k, average=True, clip=config.knn_clip,
                                                 normaliser="var" if config.knn_rms else "none"))

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        key = self.encoders.key(batch.obs, batch.next_obs, run)
        query = run(self.encoders.skill_net, self.skills(batch))
        loss = nce_loss(query, key, self.config.temperature, members=self.members)
        self.step(loss)
        return {"nce_loss": loss.detach()}

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return self.entropy(run(self.encoders.state_net, batch.next_obs))
