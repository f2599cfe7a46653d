"""ComSD's reward on CIC's contrastive module (docs/methods.md, "ComSD").

ComSD keeps CIC's encoders and NCE update (:class:`~dvfb.rewards.contrastive.CICReward`) and adds
the contrastive term to the reward with a skill-dependent weight:

``r = r_exp + beta(z) * r_div``, where

* ``r_exp`` is CIC's APT particle entropy of ``g(s_{t+n})`` (batch against itself, running
  variance, clip, ``log(1 + .)``);
* ``r_div = exp(q_i . kappa_i / T)`` with ``q_i = normalize(k(z_i))`` the row's real skill query
  and ``kappa_i = normalize(pred(g(s_t), g(s_{t+n})))`` its transition key: the numerator of the
  NCE ratio (:func:`diversity_reward`);
* ``beta(z)`` maps each skill deterministically and monotonically into
  ``[weight_low, weight_high]`` (:func:`skill_weight`).

No DMC implementation of ComSD is public: the skill, its prior and period, the weight mapping and
range, and the absence of any further reward scaling are our decisions (docs/methods.md, "ComSD").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import call_network
from dvfb.nets.members import member_mean
from dvfb.rewards.base import Runner
from dvfb.rewards.contrastive import CICReward, CICSkillConfig

WEIGHT_MAPPINGS = ("first", "mean")


@dataclass
class ComSDConfig(CICSkillConfig):
    """CIC's skill, module and APT reward (inherited fields; CIC's skill is our choice, as no DMC code
    of ComSD is public) and the weight of ComSD's diversity term."""
    weight_low: float = param(0.5, "Weight beta of the diversity reward at the low end of the skill mapping.")
    weight_high: float = param(1.0, "Weight beta of the diversity reward at the high end of the skill mapping.")
    weight_mapping: str = param("first", "How a skill z in [0,1]^d sets beta = low + (high - low) * m(z): m = z_1, "
                                "its first coordinate (uniform over skills), or the mean coordinate (close "
                                "to 1/2 for large d).", WEIGHT_MAPPINGS)


def diversity_reward(query: torch.Tensor, key: torch.Tensor, temperature: float) -> torch.Tensor:
    """``exp(cos(q_i, kappa_i) / T)`` of every row, ``(N, 1)``: the positive-pair term of the NCE
    loss, normalised exactly as :func:`~dvfb.rewards.contrastive.nce_loss` does."""
    q = F_nn.normalize(query, dim=-1)
    k = F_nn.normalize(key, dim=-1)
    return torch.exp((q * k).sum(dim=-1, keepdim=True) / temperature)


def skill_weight(skill: torch.Tensor, low: float, high: float, mapping: str = "first") -> torch.Tensor:
    """``beta(z) = low + (high - low) * m(z)``, ``(N, 1)``; ``m`` is ``z_1`` or the mean coordinate."""
    if mapping not in WEIGHT_MAPPINGS:
        raise ConfigError(f"weight_mapping must be one of {WEIGHT_MAPPINGS}, got {mapping!r}")
    m = skill[..., :1] if mapping == "first" else skill.mean(dim=-1, keepdim=True)
    return low + (high - low) * m


class ComSDReward(CICReward):
    """CIC's NCE step (inherited :meth:`update`), then ``r_exp + beta(z) * r_div`` with the updated
    encoders."""

    config: ComSDConfig

    def __init__(self, obs_dim: int, skill_dim: int, config: ComSDConfig):
        super().__init__(obs_dim, skill_dim, config)
        if config.weight_mapping not in WEIGHT_MAPPINGS:
            raise ConfigError(f"weight_mapping must be one of {WEIGHT_MAPPINGS}, got {config.weight_mapping!r}")

    @torch.no_grad()
    def reward_terms(self, batch: Batch, run: Runner = call_network
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(r_exp, r_div, beta)``, each ``(N, 1)``. Advances the running variance of the kNN
        distances, so it is called once per update (as CIC's score)."""
        c = self.config
        r_exp = super().score(batch, run)
        key = self.encoders.key(batch.obs, batch.next_obs, run)
        query = run(self.encoders.skill_net, self.skills(batch))
        r_div = diversity_reward(query, key, c.temperature)
        beta = skill_weight(self.skills(batch), c.weight_low, c.weight_high, c.weight_mapping)
        return r_exp, r_div, beta

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        r_exp, r_div, beta = self.reward_terms(batch, run)
        return r_exp + beta * r_div

    def update_and_score(self, batch: Batch, metrics: dict, run: Runner = call_network) -> torch.Tensor:
        metrics.update(self.update(batch, run))
        r_exp, r_div, beta = self.reward_terms(batch, run)
        metrics.update(exploration_reward=member_mean(r_exp, self.members),
                       diversity_reward=member_mean(r_div, self.members))
        return r_exp + beta * r_div
