"""ICM-APT as a stand-alone exploration method (docs/methods.md, "ICM-APT"): the DDPG core trained on
the kNN particle entropy of an ICM representation of ``s_t``; the representation learns from the
forward and inverse models on ``(s_t, a_t, s_{t+n})``."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.rewards.icm import ICMAPTConfig, ICMAPTReward


class ICMAPTAgent(IntrinsicDDPGAgent):
    name = "icm_apt"
    reward_section = "icm_apt"

    def build_reward(self) -> ICMAPTReward:
        return ICMAPTReward(self.obs_dim, self.action_dim, self.reward_config)


register(AgentSpec(
    name="icm_apt", agent_cls=ICMAPTAgent, family="exploration",
    summary="ICM-APT: DDPG on the kNN entropy of an ICM representation (Liu & Abbeel, URLB)",
    sections={"ddpg": DDPGConfig, "icm_apt": ICMAPTConfig}, zero_shot="single_policy", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "icm_apt": {"hidden_dim": 256, "rep_dim": 128}}}))
