"""SMM as a skill-discovery method (docs/methods.md, "SMM"): the DDPG core conditioned on a 4-way
one-hot skill drawn at every episode start, trained on a VAE density term plus a skill
discriminator term of the current state ``s_t``."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.smm import SMMConfig, SMMReward


class SMMAgent(IntrinsicDDPGAgent):
    name = "smm"
    reward_section = "smm"

    def declare_skill(self) -> SkillSpec:
        # URLB's net effect: a uniform skill per episode, never resampled within one.
        return SkillSpec("one_hot", self.reward_config.skill_dim, every=None)

    def build_reward(self) -> SMMReward:
        return SMMReward(self.obs_dim, self.skill.dim, self.reward_config)


register(AgentSpec(
    name="smm", agent_cls=SMMAgent, family="skill_discovery",
    summary="SMM: DDPG on one-hot skills rewarded by a VAE density and a skill discriminator "
            "(Lee et al., URLB)",
    sections={"ddpg": DDPGConfig, "smm": SMMConfig}, zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "smm": {"hidden_dim": 256}}}))
