"""Dual-value fine-tuning with reward mapping, for any model of the FB family (docs/methods.md §9).

F and B are frozen; a freshly initialised twin task critic Q_F learns from the downstream reward
rescaled so that its running mean matches the running mean of FB's implicit reward, and the
actor maximises ``qf_coef * Q_F + eta * Q_M``. Variants (§9.6): w/o SVF is ``eta = 0``, w/o MAP is
``reward_mapping = false``, and ``eta_mode = adaptive`` uses ``eta_i = Q_F,i / Q_M,i`` (detached).

It reads the model through its interface only (:class:`~dvfb.agents.base.Model`): the actor, the
forward map whose ``F . z`` is the skill value (FB's F, SF's psi), the features of transitions
(``backward_features``: B, or SF's phi) and the training settings; every network call goes through
the model's ``net_runner``, so ``--perf.precision`` and ``--perf.compile`` apply.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from dvfb.agents.base import Model, ReplayNeeds
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import (
    RunningMeanStd,
    TwinCritic,
    adam,
    freeze_,
    implicit_reward,
    make_target,
    skill_values,
    soft_update_,
    training_action,
    twin_td_loss,
)
from dvfb.nets.members import member_mean, minimise, per_member
from dvfb.protocols.base import Finetuner, FinetuneSchedule, register_finetuner


@dataclass
class FinetuneConfig(FinetuneSchedule):
    """Dual-value fine-tuning of the FB family: the protocol plus the options of §9, §12, §14."""

    eta: float = param(0.5, "Weight of the skill value Q_M in the actor objective; 0 = w/o SVF (D3).", at_least=0)
    eta_mode: str = param("constant", "constant eta, or adaptive eta_i = Q_F,i / Q_M,i.", ("constant", "adaptive"))
    qf_coef: float = param(1.0, "Weight of Q_F in the actor objective (authors' code: 50 with eta = 1).", at_least=0)
    reward_mapping: bool = param(True, "Map the task reward to the implicit reward's scale; false = w/o MAP.")
    reward_map_eps: float = param(1e-8, "eps in r * mu_fb / (mu_t + eps).", at_least=0)
    reward_map_abs: bool = param(False, "Use |mu_fb| so a negative implicit mean cannot flip the reward sign.")
    reward_map_clip: float | None = param(None, "Clip mapped rewards to [-c, c]; none = no clip.", above=0)
    cov_ridge: float = param(0.0, "Ridge added to Cov(B) in the implicit reward.", at_least=0)
    keep_inference_data: bool = param(False, "Seed the fine-tuning buffer with the inference transitions (D12).")


@register_finetuner
class DualValueFinetuner(Finetuner):
    """Q_F training and the dual-value actor on top of a pre-trained FB-family agent (§9.2-§9.5).

    Rollouts use ``pi(s, z_r)`` from the first step (no uniform phase, §9.1).
    """

    name = "dual_value"
    config_cls = FinetuneConfig
    uniform_seed_actions = False

    def __init__(self, model: Model, z: torch.Tensor, config: FinetuneConfig):
        nn.Module.__init__(self)
        self.model, self.config = model, config
        settings = model.settings
        # Everything pre-trained but the actor stays fixed (F and B; SF's psi and phi).
        for module in model.snapshot_modules().values():
            if module is not model.actor:
                freeze_(module)
        self.register_buffer("z", z.detach().clone().to(model.device))
        self.task_critic = TwinCritic(model.obs_dim, model.action_dim, model.skill_dim,
                                      settings.hidden_dim).to(model.device)
        self.task_critic_target = make_target(self.task_critic)
        self.implicit_reward_stats = RunningMeanStd().to(model.device)
        self.task_reward_stats = RunningMeanStd().to(model.device)
        self.critic_optimizer = adam(self.task_critic.parameters(), settings.lr, settings.fused_adam)
        # A fresh actor optimiser (§3.6: the authors do not carry the pre-training state over).
        self.actor_optimizer = adam(model.actor.parameters(), settings.lr, settings.fused_adam)

    @classmethod
    def check(cls, model: Model, config: FinetuneConfig) -> None:
        if not model.learns_skill_value:
            raise ConfigError(f"dual-value fine-tuning needs a model with a skill value (the FB family); "
                              f"{model.name!r} has none")

    def update_networks(self) -> list[nn.Module]:
        return [self.model.actor, self.model.forward_map, self.task_critic, self.task_critic_target]

    @property
    def skill(self) -> torch.Tensor:
        return self.z

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"task_critic": self.critic_optimizer, "actor": self.actor_optimizer}

    @classmethod
    def keeps_inference_data(cls, config: FinetuneConfig) -> bool:
        return config.keep_inference_data

    @classmethod
    def needs_of(cls, model: Model) -> ReplayNeeds:
        return ReplayNeeds(model.settings.batch_size, model.settings.discount)

    def mapped_reward(self, batch: Batch, metrics: dict) -> torch.Tensor:
        """``r_f = r * mu_fb / (mu_t + eps)`` with running means (§9.4 steps 1-3). ``(N, 1)``
        (a group's: ``(M, N, 1)``, each member's rescaled by its own means)."""
        c = self.config
        reward = batch.reward
        if not c.reward_mapping:
            return reward
        with torch.no_grad():
            features = self.model.backward_features(batch.obs, batch.next_obs)
            implicit = implicit_reward(features, self.z, c.cov_ridge)
            mu_fb, _ = self.implicit_reward_stats.update(implicit)
            mu_t, _ = self.task_reward_stats.update(reward)
            if c.reward_map_abs:
                mu_fb = mu_fb.abs()
            scale = (mu_fb / (mu_t + c.reward_map_eps)).to(reward.dtype)
            mapped = reward * per_member(scale, reward)
            if c.reward_map_clip is not None:
                mapped = mapped.clamp(-c.reward_map_clip, c.reward_map_clip)
        metrics["implicit_reward_mean"] = mu_fb.float()
        metrics["task_reward_mean"] = mu_t.float()
        metrics["mapped_reward"] = member_mean(mapped, self.members)
        return mapped

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        settings = self.model.settings
        actor, run = self.model.actor, self.net_runner
        metrics: dict[str, torch.Tensor] = {}
        members = self.members
        # One z per row: (N, d), or (M, N, d) in a group (each member's own z_r); the twin heads'
        # axis is -3 of the critic's values and -2 of the skill values either way.
        z = self.z.unsqueeze(-2).expand(*batch.obs.shape[:-1], -1)
        reward = self.mapped_reward(batch, metrics)
        with torch.no_grad():
            next_action = training_action(run(actor, batch.next_obs, z), settings.stddev, settings.stddev_clip,
                                          self.generator)
            next_q = run(self.task_critic_target, batch.next_obs, z, next_action).amin(-3)
            target = reward + batch.discount * next_q
        q = run(self.task_critic, batch.obs, z, batch.action)
        critic_loss = twin_td_loss(q, target)
        minimise(self.critic_optimizer, critic_loss)

        action = training_action(run(actor, batch.obs, z), settings.stddev, settings.stddev_clip, self.generator)
        task_value = run(self.task_critic, batch.obs, z, action).amin(-3).squeeze(-1)
        objective = self.config.qf_coef * task_value
        if self.config.eta != 0 or self.config.eta_mode == "adaptive":
            skill_value = skill_values(run(self.model.forward_map, batch.obs, action, z), z).amin(-2)
            eta = (task_value / skill_value).detach() if self.config.eta_mode == "adaptive" else self.config.eta
            objective = objective + eta * skill_value
            metrics["skill_value"] = member_mean(skill_value.detach(), members)
        actor_loss = -member_mean(objective, members)
        minimise(self.actor_optimizer, actor_loss, inputs=list(actor.parameters()))
        soft_update_(self.task_critic_target, self.task_critic, settings.tau)
        metrics.update(task_critic_loss=critic_loss.detach(), actor_loss=actor_loss.detach(),
                       task_value=member_mean(task_value.detach(), members))
        return metrics

    def training_state(self) -> dict:
        return {"actor": self.model.actor.state_dict(),
                "finetuner": {k: v for k, v in self.state_dict().items() if not k.startswith("model.")},
                "optimizers": {"critic": self.critic_optimizer.state_dict(),
                               "actor": self.actor_optimizer.state_dict()}}

    def load_training_state(self, state: dict) -> None:
        self.model.actor.load_state_dict(state["actor"])
        own = {k: v for k, v in self.state_dict().items() if not k.startswith("model.")}
        missing = set(own) - set(state["finetuner"])
        if missing:
            raise KeyError(f"fine-tuning checkpoint lacks {sorted(missing)}")
        self.load_state_dict({**self.state_dict(), **state["finetuner"]})
        self.critic_optimizer.load_state_dict(state["optimizers"]["critic"])
        self.actor_optimizer.load_state_dict(state["optimizers"]["actor"])
