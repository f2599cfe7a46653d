"""BeCL (docs/methods.md, "BeCL"): the DDPG core conditioned on a one-hot skill and trained on
``exp(-loss_i)`` of a behaviour-contrastive loss over ``f(s_{t+n})``.

One agent update draws ``contrastive_update_rate * B`` rows, i.e. that many independent batches of
``B``: each gets one contrastive step, and the last one is then scored and feeds the DDPG step.
"""

from __future__ import annotations

import torch

from dvfb.agents.base import ReplayNeeds
from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.data import Batch
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.becl import BeCLConfig, BeCLReward

__all__ = ["BeCLAgent", "BeCLConfig"]


class BeCLAgent(IntrinsicDDPGAgent):
    name = "becl"
    reward_section = "becl"

    def declare_skill(self) -> SkillSpec:
        c = self.reward_config
        return SkillSpec("one_hot", c.skill_dim, every=c.skill_every)

    def build_reward(self) -> BeCLReward:
        return BeCLReward(self.obs_dim, self.skill.dim, self.reward_config)

    def replay_needs(self) -> ReplayNeeds:
        # rate * B uniform draws are rate independent batches of B (the official code's fresh
        # batch per contrastive step), in one sampling call.
        rate = self.reward_config.contrastive_update_rate
        return ReplayNeeds(rate * self.ddpg.batch_size, self.ddpg.discount, nstep=self.ddpg.nstep)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """``rate`` contrastive steps on fresh batches, then reward and DDPG step on the last one."""
        metrics: dict[str, torch.Tensor] = {}
        parts = batch.chunk(self.reward_config.contrastive_update_rate)
        for part in parts:
            metrics.update(self.intrinsic.update(part, self.net_runner))  # logs the last step's loss
        last = parts[-1]
        with torch.no_grad():
            reward = self.intrinsic.score(last, self.net_runner)
        self.core.update(last, reward, metrics, self.net_runner)  # logs the reward's mean as "reward"
        return metrics


register(AgentSpec(
    name="becl", agent_cls=BeCLAgent, family="skill_discovery",
    summary="BeCL: DDPG on one-hot skills rewarded by a behaviour-contrastive loss over s_{t+n} (Yang et al.)",
    sections={"ddpg": DDPGConfig, "becl": BeCLConfig},
    zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "becl": {"hidden_dim": 256}}}))
