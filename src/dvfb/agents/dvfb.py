"""DVFB: FB plus an exploration critic driven by RND + contrastive-entropy rewards.

algorithm.md §0, §7.2-§7.7, §7.11. The skill value Q_M = F . z keeps learning the successor
measure; a separate z-conditioned twin critic Q_P learns from the intrinsic reward
``r_rnd + beta * r_ce`` and the actor maximises ``Q_M + alpha * Q_P``. "DVFB w/o CE" is
``use_ce = false`` (no contrastive module at all, ``r = r_rnd``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dvfb.agents.fb import FBAgent, FBConfig, adam
from dvfb.agents.perf import PerfConfig
from dvfb.agents.intrinsic import (
    CE_AGGREGATES,
    CE_NEIGHBOURS,
    RNDReward,
    contrastive_entropy_reward,
    nce_loss,
)
from dvfb.config import param
from dvfb.nets import ContrastiveEncoders, TwinCritic, make_target
from dvfb.replay import Batch


@dataclass
class ExplorationConfig:
    """DVFB's exploration part (algorithm.md §7.3-§7.7, §14). Ignored by the FB agent."""

    alpha: float = param(5.0, "Weight of Q_P in the actor objective (D2; authors' code: 50).")
    alpha_mode: str = param("constant", "constant alpha, or adaptive alpha_t = 2 mean(Q_M)/mean(Q_P).",
                            ("constant", "adaptive"))
    beta: float = param(0.5, "Weight of the contrastive-entropy reward (D4).")
    use_ce: bool = param(True, "Use the contrastive-entropy term; false gives 'DVFB w/o CE'.")
    rnd_input: str = param("next_obs", "Which state RND scores: s' (paper) or s (authors' code), D6.",
                           ("next_obs", "obs"))
    rnd_rep_dim: int = param(512, "Output width of the RND networks.")
    rnd_obs_clip: float = param(5.0, "Clip of the batch-normalised RND input.")
    contrastive_hidden_dim: int = param(1024, "Hidden width of the contrastive encoders.")
    ce_k: int = param(12, "Number of neighbours k of the CE reward.")
    ce_neighbours: str = param("least_similar", "Which skills are the CE neighbours (D7).", CE_NEIGHBOURS)
    ce_aggregate: str = param("log_of_mean", "log of the mean or mean of the logs (D7).", CE_AGGREGATES)
    ce_temperature: float = param(1.0, "Temperature of the CE reward.")
    nce_temperature: float = param(1.0, "Temperature T of the NCE loss (D14).")
    nce_exact_positive: bool = param(False, "Subtract the exact positive term in the NCE denominator.")


class DVFBAgent(FBAgent):
    """FB + exploration critic Q_P (algorithm.md §7)."""

    name = "dvfb"

    def __init__(self, obs_dim: int, action_dim: int, config: FBConfig, exploration: ExplorationConfig,
                 device: str | torch.device = "cpu", perf: PerfConfig | None = None):
        self.exploration = exploration
        super().__init__(obs_dim, action_dim, config, device, perf)

    def _build_extra(self) -> None:
        c, e = self.config, self.exploration
        self.exploration_critic = TwinCritic(self.obs_dim, self.action_dim, c.z_dim, c.hidden_dim)
        self.exploration_critic_target = make_target(self.exploration_critic)
        self.rnd = RNDReward(self.obs_dim, c.hidden_dim, e.rnd_rep_dim, e.rnd_obs_clip)
        # The skill labels are B's outputs, so the encoders' skill dimension is z_dim (§4.6).
        self.contrastive = (ContrastiveEncoders(self.obs_dim, c.z_dim, e.contrastive_hidden_dim)
                            if e.use_ce else None)

    def _build_extra_optimizers(self) -> None:
        c = self.config
        self.critic_optimizer = adam(self.exploration_critic.parameters(), c.lr, c.fused_adam)
        self.rnd_optimizer = adam(self.rnd.predictor_parameters(), c.lr, c.fused_adam)
        self.contrastive_optimizer = (adam(self.contrastive.parameters(), c.lr, c.fused_adam)
                                      if self.contrastive is not None else None)

    def target_pairs(self):
        return super().target_pairs() + [(self.exploration_critic_target, self.exploration_critic)]

    def update_networks(self):
        nets = super().update_networks() + [self.exploration_critic, self.exploration_critic_target,
                                            self.rnd.networks.predictor, self.rnd.networks.target]
        if self.contrastive is not None:
            nets += [self.contrastive.state_net, self.contrastive.transition_net, self.contrastive.skill_net]
        return nets

    def _actor_loss_frozen(self):
        return super()._actor_loss_frozen() + [self.exploration_critic]

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opts = super().optimizers()
        opts.update(critic_optimizer=self.critic_optimizer, rnd_optimizer=self.rnd_optimizer)
        if self.contrastive_optimizer is not None:
            opts["contrastive_optimizer"] = self.contrastive_optimizer
        return opts

    # Intrinsic reward ----------------------------------------------------------------------------
    def intrinsic_reward(self, batch: Batch, labels: torch.Tensor, metrics: dict) -> torch.Tensor:
        """RND step, NCE step, then ``r_rnd + beta * r_ce`` with the updated modules (§7.2 steps 3-6)."""
        e = self.exploration
        run = self.net_runner
        rnd_obs = batch.next_obs if e.rnd_input == "next_obs" else batch.obs
        normed, rnd_target = self.rnd.prepare(rnd_obs, run)
        rnd_loss = self.rnd.loss(normed, rnd_target, run)
        self.rnd_optimizer.zero_grad(set_to_none=True)
        rnd_loss.backward()
        self.rnd_optimizer.step()
        metrics["rnd_loss"] = rnd_loss.detach()

        if self.contrastive is not None:
            key = self.contrastive.key(batch.obs, batch.next_obs, run)
            query = run(self.contrastive.skill_net, labels)
            loss = nce_loss(query, key, e.nce_temperature, e.nce_exact_positive)
            self.contrastive_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.contrastive_optimizer.step()
            metrics["nce_loss"] = loss.detach()

        reward = self.rnd.reward(normed, rnd_target, run)
        metrics["rnd_reward"] = reward.mean()
        if self.contrastive is not None and e.beta != 0:
            with torch.no_grad():  # the just-updated encoders (§7.2 step 6)
                key = self.contrastive.key(batch.obs, batch.next_obs, run)
                query = run(self.contrastive.skill_net, labels)
                ce = contrastive_entropy_reward(key, query, e.ce_k, e.ce_neighbours, e.ce_aggregate,
                                                e.ce_temperature)
            metrics["ce_reward"] = ce.mean()
            reward = reward + e.beta * ce
        metrics["intrinsic_reward"] = reward.mean()
        return reward

    def exploration_critic_loss(self, batch: Batch, z: torch.Tensor, next_action: torch.Tensor,
                                reward: torch.Tensor) -> torch.Tensor:
        """Twin TD loss of Q_P on the intrinsic reward (§7.7)."""
        run = self.net_runner
        with torch.no_grad():
            next_q = run(self.exploration_critic_target, batch.next_obs, z, next_action).amin(0)  # (N, 1)
            target = reward + batch.discount * next_q
        q = run(self.exploration_critic, batch.obs, z, batch.action)  # (2, N, 1)
        return (q - target).pow(2).mean(dim=(1, 2)).sum()

    def _explore(self, batch, z, next_action, labels, metrics) -> None:
        reward = self.intrinsic_reward(batch, labels, metrics)
        loss = self.exploration_critic_loss(batch, z, next_action, reward)
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        metrics["exploration_critic_loss"] = loss.detach()

    def _actor_bonus(self, obs, z, action, skill_value, metrics):
        e = self.exploration
        exploration_value = self.net_runner(self.exploration_critic, obs, z, action).amin(0).squeeze(-1)
        if e.alpha_mode == "adaptive":
            alpha = (2 * skill_value.mean() / exploration_value.mean()).detach()
        else:
            alpha = e.alpha
        metrics["exploration_value"] = exploration_value.detach().mean()
        return alpha * exploration_value
