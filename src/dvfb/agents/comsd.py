"""ComSD (docs/methods.md, "ComSD"): CIC's skill, encoders and NCE update, with the reward
``APT(g(s_{t+n})) + beta(z) * exp(q . kappa / T)``: particle entropy plus a contrastive diversity
term whose weight depends on the skill. The DMC settings are our decisions (no public DMC code)."""

from __future__ import annotations

from dvfb.agents.cic import CICAgent
from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig
from dvfb.agents.registry import AgentSpec, register
from dvfb.rewards.comsd import ComSDConfig, ComSDReward

__all__ = ["ComSDAgent", "ComSDConfig"]


class ComSDAgent(CICAgent):
    """CIC's skill and update; only the reward differs."""

    name = "comsd"
    reward_section = "comsd"

    def build_reward(self) -> ComSDReward:
        return ComSDReward(self.obs_dim, self.skill.dim, self.reward_config)


register(AgentSpec(
    name="comsd", agent_cls=ComSDAgent, family="skill_discovery",
    summary="ComSD: CIC's contrastive skills with a skill-weighted contrastive diversity reward added to "
            "the particle entropy (Liu, Chen & Zhao)",
    sections={"ddpg": DDPGConfig, "comsd": ComSDConfig},
    zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "comsd": {"hidden_dim": 256}}}))
