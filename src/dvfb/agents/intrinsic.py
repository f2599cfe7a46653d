"""Intrinsic rewards shared by DVFB and the exploration baselines.

* :func:`nce_loss` -- the contrastive (NCE) loss of the CIC-style encoders (algorithm.md §7.4);
* :func:`contrastive_entropy_reward` -- the kNN contrastive-entropy reward from one matrix product
  and a top-k, never an N x N x d tensor (§7.5, D7);
* :class:`RNDReward` -- RND novelty normalised by the running std of its error (§4.5, §7.3, §7.6).
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.nets import RNDNetworks, RunningMeanStd, call_network

CE_NEIGHBOURS = ("least_similar", "most_similar")
CE_AGGREGATES = ("log_of_mean", "mean_of_log")


def nce_loss(query: torch.Tensor, key: torch.Tensor, temperature: float = 1.0,
             exact_positive: bool = False) -> torch.Tensor:
    """Mean over rows of ``-log(exp(S_ii) / (neg_i + 1e-6))`` with ``S = q k^T / T`` (§7.4).

    ``neg_i = max(sum_j exp(S_ij) - e^{1/T}, 1e-6)``: the CIC trick removes the upper bound of the
    positive term. With ``exact_positive`` the exact ``exp(S_ii)`` is removed instead.
    """
    q = F_nn.normalize(query, dim=-1)
    k = F_nn.normalize(key, dim=-1)
    sim = q @ k.T / temperature
    exp_sim = sim.exp()
    positive = sim.diagonal()
    subtract = exp_sim.diagonal() if exact_positive else math.exp(1.0 / temperature)
    negative = (exp_sim.sum(-1) - subtract).clamp_min(1e-6)
    return (torch.log(negative + 1e-6) - positive).mean()


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
    cos = F_nn.normalize(key, dim=-1) @ F_nn.normalize(query, dim=-1).T  # (N, N)
    k = min(k, cos.shape[-1])
    nearest = cos.topk(k, dim=-1, largest=(neighbours == "most_similar")).values
    distance = (1.0 - nearest / temperature).clamp_min(0.0)
    if aggregate == "log_of_mean":
        return torch.log1p(distance.mean(-1, keepdim=True))
    return torch.log1p(distance).mean(-1, keepdim=True)


class RNDReward(nn.Module):
    """RND module with its running error statistics and optimiser-facing loss (§7.3, §7.6)."""

    def __init__(self, obs_dim: int, hidden_dim: int, rep_dim: int = 512, obs_clip: float = 5.0):
        super().__init__()
        self.networks = RNDNetworks(obs_dim, hidden_dim, rep_dim, obs_clip)
        self.error_stats = RunningMeanStd()

    def predictor_parameters(self):
        return self.networks.predictor.parameters()

    def prepare(self, obs: torch.Tensor, run: Callable = call_network) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised input and the frozen target's output: computed once, used twice.

        ``run(net, x)`` calls a network (the agent passes its :class:`~dvfb.agents.perf.NetRunner`).
        """
        normed = self.networks.normalise(obs)
        with torch.no_grad():
            target = run(self.networks.target, normed)
        return normed, target

    def loss(self, normed: torch.Tensor, target: torch.Tensor, run: Callable = call_network) -> torch.Tensor:
        return RNDNetworks.error(run(self.networks.predictor, normed), target).mean()

    @torch.no_grad()
    def reward(self, normed: torch.Tensor, target: torch.Tensor, run: Callable = call_network) -> torch.Tensor:
        """``e(x) / (sqrt(S_rnd) + 1e-8)`` after folding this batch into the statistics. ``(N, 1)``."""
        error = RNDNetworks.error(run(self.networks.predictor, normed), target)
        _mean, var = self.error_stats.update(error)
        return (error / (var.sqrt().to(error.dtype) + 1e-8)).unsqueeze(-1)
