"""CIC as a stand-alone skill-discovery method (docs/methods.md, "CIC"): the DDPG core conditioned
on a 64-d skill from Uniform[0, 1]^64, trained on the APT particle entropy of the state encoder's
``g(s_{t+n})``; the encoder learns from the NCE loss between skills and transitions."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.contrastive import CICReward, CICSkillConfig


class CICAgent(IntrinsicDDPGAgent):
    name = "cic"
    reward_section = "cic"

    def declare_skill(self) -> SkillSpec:
        c = self.reward_config
        return SkillSpec("box", c.skill_dim, every=c.skill_every, low=0.0, high=1.0)

    def build_reward(self) -> CICReward:
        return CICReward(self.obs_dim, self.skill.dim, self.reward_config)


register(AgentSpec(
    name="cic", agent_cls=CICAgent, family="skill_discovery",
    summary="CIC: DDPG on skills in [0,1]^64, APT entropy of a contrastively learnt encoder (Laskin et al.)",
    sections={"ddpg": DDPGConfig, "cic": CICSkillConfig}, zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "cic": {"hidden_dim": 256}}}))
