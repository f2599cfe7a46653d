"""APS as a skill-discovery method (docs/methods.md, "APS"): the DDPG core with a successor-feature
critic ``Q_k = psi_k(s, w, a) . w``, conditioned on a unit task ``w`` redrawn every 5 steps and
trained on a particle-entropy plus successor-feature reward of ``s_{t+n}``."""

from __future__ import annotations

import torch
from torch import nn

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, DDPGCore, DDPGModel, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.nets import TwinCritic, call_network
from dvfb.nets.members import with_head_axis
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.aps import APSConfig, APSReward


class APSCore(DDPGCore):
    """DDPG with a successor-feature critic: the twin heads output ``psi_k`` ``(d,)`` and the value
    is ``psi_k . w``; losses, target and EMA are the DDPG core's."""

    def build_critic(self) -> nn.Module:
        c = self.config
        return TwinCritic(self.obs_dim, self.action_dim, self.skill_dim, c.hidden_dim, out_dim=self.skill_dim)

    def critic_values(self, critic: nn.Module, obs: torch.Tensor, skill: torch.Tensor, action: torch.Tensor,
                      run=call_network) -> torch.Tensor:
        psi = run(critic, obs, skill, action)  # (K, N, d)
        return (psi * with_head_axis(skill, self.members)).sum(dim=-1, keepdim=True)  # (K, N, 1)


class APSModel(DDPGModel):
    """APS's pre-trained agent: the core and its reward module, whose features regress a task's
    rewards into a skill (URLB's fine-tuning task regression)."""

    def regress_skill(self, obs: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.intrinsic.regress_task(obs, reward, self.net_runner)


class APSAgent(IntrinsicDDPGAgent):
    name = "aps"
    reward_section = "aps"
    core_cls = APSCore
    model_cls = APSModel

    def declare_skill(self) -> SkillSpec:
        c = self.reward_config
        return SkillSpec("sphere", c.skill_dim, every=c.skill_every, radius=1.0)

    def build_reward(self) -> APSReward:
        return APSReward(self.obs_dim, self.skill.dim, self.reward_config)


register(AgentSpec(
    name="aps", agent_cls=APSAgent, family="skill_discovery",
    summary="APS: DDPG with successor features on unit tasks, rewarded by kNN entropy plus w . phi "
            "(Liu & Abbeel)",
    sections={"ddpg": DDPGConfig, "aps": APSConfig}, zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "aps": {"hidden_dim": 256}}}))
