"""DIAYN as a skill-discovery method (docs/methods.md, "DIAYN"): the DDPG core conditioned on a
16-way one-hot skill, trained on how well a discriminator recognises the skill from ``s_{t+n}``."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.diayn import DIAYNConfig, DIAYNReward

class DIAYNAgent(IntrinsicDDPGAgent):
    name = "diayn"
    reward_section = "diayn"

    def declare_skill(self) -> SkillSpec:
        c = self.reward_config
        return SkillSpec("one_hot", c.skill_dim, every=c.skill_every)

    def build_reward(self) -> DIAYNReward:
        return DIAYNReward(self.obs_dim, self.skill.dim, self.reward_config)


register(AgentSpec(
    name="diayn", agent_cls=DIAYNAgent, family="skill_discovery",
    summary="DIAYN: DDPG on one-hot skills rewarded by a skill discriminator on s_{t+n} (Eysenbach et al.)",
    sections={"ddpg": DDPGConfig, "diayn": DIAYNConfig}, zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "diayn": {"hidden_dim": 256}}}))
