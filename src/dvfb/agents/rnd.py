"""RND as a stand-alone exploration method (docs/methods.md, "RND"): the DDPG core trained on RND
novelty of the current state ``s_t`` (URLB scores s_t; DVFB's own RND term scores s_{t+1})."""

from __future__ import annotations

from dataclasses import dataclass

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.core.config import param
from dvfb.rewards.rnd import RND_INPUTS, RNDReward


@dataclass
class RNDConfig:
    """RND's predictor/target networks and their reward."""

    hidden_dim: int = param(1024, "Hidden width of the predictor and the frozen target.", at_least=1)
    rep_dim: int = param(512, "Output width of both networks.", at_least=1)
    obs_clip: float = param(5.0, "Clip of the batch-normalised input.", above=0)
    input: str = param("obs", "Which state of a batch row is scored: s_t (URLB) or s_{t+n}.", RND_INPUTS)
    scale: float = param(1.0, "Multiplier of the normalised novelty.", at_least=0)
    lr: float = param(1e-4, "Adam learning rate of the predictor.", above=0)


class RNDAgent(IntrinsicDDPGAgent):
    name = "rnd"
    reward_section = "rnd"

    def build_reward(self) -> RNDReward:
        c = self.reward_config
        return RNDReward(self.obs_dim, c.hidden_dim, c.rep_dim, c.obs_clip, c.input, c.scale)


register(AgentSpec(
    name="rnd", agent_cls=RNDAgent, family="exploration",
    summary="RND: DDPG on the error of a predictor chasing a frozen random network (Burda et al.)",
    sections={"ddpg": DDPGConfig, "rnd": RNDConfig}, zero_shot="single_policy", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL, "rnd": {"hidden_dim": 256, "rep_dim": 128}}}))
