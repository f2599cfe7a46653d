"""Disagreement as a stand-alone exploration method (docs/methods.md, "Disagreement"): the DDPG core
trained on the variance of an ensemble of forward models' predictions of ``s_{t+n}``."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.rewards.disagreement import DisagreementConfig, DisagreementReward


class DisagreementAgent(IntrinsicDDPGAgent):
    name = "disagreement"
    reward_section = "disagreement"

    def build_reward(self) -> DisagreementReward:
        return DisagreementReward(self.obs_dim, self.action_dim, self.reward_config)


register(AgentSpec(
    name="disagreement", agent_cls=DisagreementAgent, family="exploration",
    summary="Disagreement: DDPG on the variance of an ensemble of forward models (Pathak et al.)",
    sections={"ddpg": DDPGConfig, "disagreement": DisagreementConfig}, zero_shot="single_policy", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "disagreement": {"hidden_dim": 256}}}))
