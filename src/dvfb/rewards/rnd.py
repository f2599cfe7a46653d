"""RND: novelty as the error of a predictor chasing a frozen random network (docs/methods.md, "RND").

* :class:`RNDNetworks` -- predictor and frozen target on batch-normalised, clipped input;
* :class:`RNDReward` -- the module with its running error statistics: ``e(x) / (sqrt(S) + 1e-8)``
  with ``S`` the running variance of the error, after a predictor step on the same batch.

DVFB scores ``s_{t+1}`` (``input="next_obs"``, the paper) or ``s_t`` (the authors' code); the RND
baseline scores ``s_t`` (URLB).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.nets import RunningMeanStd, call_network, freeze_, mlp, orthogonal_init_
from dvfb.nets.members import member_mean, per_member
from dvfb.data import Batch
from dvfb.rewards.base import IntrinsicReward, Runner

RND_INPUTS = ("next_obs", "obs")


class RNDNetworks(nn.Module):
    """RND predictor and frozen random target on batch-normalised, clipped input (§4.5).

    The normalisation is a per-dimension batch norm without affine parameters, always using the
    current batch statistics (biased variance, eps 1e-5), then a clamp to ``[-clip, clip]``.
    """

    def __init__(self, obs_dim: int, hidden_dim: int, rep_dim: int = 512, obs_clip: float = 5.0):
        super().__init__()
        self.obs_clip = obs_clip
        self.predictor = mlp(obs_dim, hidden_dim, hidden_dim, rep_dim)
        self.target = freeze_(mlp(obs_dim, hidden_dim, hidden_dim, rep_dim))
        orthogonal_init_(self)

    def normalise(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.dim() == 3:  # a group (M, N, O): each member's batch statistics, as channels M*O
            m, n, o = obs.shape
            flat = obs.transpose(0, 1).reshape(n, m * o)
            normed = F_nn.batch_norm(flat, None, None, training=True, eps=1e-5).reshape(n, m, o).transpose(0, 1)
        else:
            normed = F_nn.batch_norm(obs, None, None, training=True, eps=1e-5)
        return normed.clamp(-self.obs_clip, self.obs_clip)

    @staticmethod
    def error(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Per-sample error ``mean_k (target_k - prediction_k)^2`` -> ``(N,)``."""
        return (target - prediction).pow(2).mean(-1)


class RNDReward(IntrinsicReward):
    """RND module with its running error statistics (§4.5, §7.3, §7.6 of docs/methods.md).

    ``input`` says which state of a batch row is scored: ``"next_obs"`` or ``"obs"``; ``scale``
    multiplies the reward (URLB's rnd_scale).
    """

    def __init__(self, obs_dim: int, hidden_dim: int, rep_dim: int = 512, obs_clip: float = 5.0,
                 input: str = "next_obs", scale: float = 1.0):
        super().__init__()
        self.scale = scale
        if input not in RND_INPUTS:
            raise ValueError(f"RND input must be one of {RND_INPUTS}, got {input!r}")
        self.input = input
        self.networks = RNDNetworks(obs_dim, hidden_dim, rep_dim, obs_clip)
        self.error_stats = RunningMeanStd()

    def prepare(self, obs: torch.Tensor, run: Runner = call_network) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised input and the frozen target's output: computed once, used by the loss and the reward."""
        normed = self.networks.normalise(obs)
        with torch.no_grad():
            target = run(self.networks.target, normed)
        return normed, target

    def loss(self, normed: torch.Tensor, target: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        return member_mean(RNDNetworks.error(run(self.networks.predictor, normed), target), self.members)

    @torch.no_grad()
    def reward(self, normed: torch.Tensor, target: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        """``e(x) / (sqrt(S_rnd) + 1e-8)`` after folding this batch into the statistics. ``(N, 1)``."""
        error = RNDNetworks.error(run(self.networks.predictor, normed), target)
        _mean, var = self.error_stats.update(error)
        reward = (error / (per_member(var, error).sqrt().to(error.dtype) + 1e-8)).unsqueeze(-1)
        return reward * self.scale if self.scale != 1.0 else reward

    def _scored(self, batch: Batch) -> torch.Tensor:
        return batch.next_obs if self.input == "next_obs" else batch.obs

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        normed, target = self.prepare(self._scored(batch), run)
        loss = self.loss(normed, target, run)
        self.step(loss)
        return {"rnd_loss": loss.detach()}

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return self.reward(*self.prepare(self._scored(batch), run), run)

    def update_and_score(self, batch: Batch, metrics: dict, run: Runner = call_network) -> torch.Tensor:
        # The normalised input and the target's output serve the step and the reward.
        normed, target = self.prepare(self._scored(batch), run)
        loss = self.loss(normed, target, run)
        self.step(loss)
        metrics["rnd_loss"] = loss.detach()
        reward = self.reward(normed, target, run)
        metrics["rnd_reward"] = member_mean(reward, self.members)
        return reward
