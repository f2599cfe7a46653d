"""Proto as a stand-alone exploration method (docs/methods.md, "Proto"): the DDPG core trained on the
distance of ``s_{t+n}``'s projection to its 3rd-nearest entry of a queue of prototype candidates.
Fine-tuning copies the whole pre-trained critic (URLB's Proto), not only its trunk."""

from __future__ import annotations

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.rewards.proto import ProtoConfig, ProtoReward


class ProtoAgent(IntrinsicDDPGAgent):
    name = "proto"
    reward_section = "proto"

    def build_reward(self) -> ProtoReward:
        return ProtoReward(self.obs_dim, self.action_dim, self.reward_config)


register(AgentSpec(
    name="proto", agent_cls=ProtoAgent, family="exploration",
    summary="Proto: DDPG on a prototype-queue kNN distance of the next state (Yarats et al.)",
    sections={"ddpg": DDPGConfig, "proto": ProtoConfig}, zero_shot="single_policy", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL}}, defaults={"finetune": {"init_critic": "all"}}))
