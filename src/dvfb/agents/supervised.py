"""The supervised reference (docs/methods.md, "Supervised reference"): the DDPG core trained from
scratch, online, on one task's own reward, with the budget of the reward-free rows.

Its results are the denominators of the reports' normalised scores (docs/reports.md). It runs as a
pre-training run whose environment is the task (``supervised.task``): the same run directory,
checkpoints, exact resume, snapshots and sweeps as every method; ``dvfb supervised`` is the
command. Its zero-shot protocol is the single policy, evaluated on its own task only.
"""

from __future__ import annotations

from dataclasses import dataclass

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.core.config import param
from dvfb.rewards.extrinsic import TaskReward


@dataclass
class SupervisedConfig:
    """Which task the reference learns."""

    task: str = param("", "The task whose reward it trains on, a task of --domain; empty: the domain's "
                      "pre-training task (walker: walker_walk).")


class SupervisedAgent(IntrinsicDDPGAgent):
    name = "supervised"
    reward_section = "supervised"

    def build_reward(self) -> TaskReward:
        return TaskReward()


register(AgentSpec(
    name="supervised", agent_cls=SupervisedAgent, family="reference",
    summary="supervised reference: DDPG from scratch on the task's own reward (the normaliser of the reports)",
    sections={"ddpg": DDPGConfig, "supervised": SupervisedConfig}, zero_shot="single_policy", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL}}, column=900,
    task_field="supervised.task"))
