"""The DDPG core every URLB-style method stands on, and its fine-tuner (docs/methods.md, "DDPG core").

* :class:`DDPGConfig` -- the backbone's hyper-parameters (hidden 1024, batch 1024, n = 3, ...);
* :class:`DDPGCore` -- actor ``mu(s, skill)`` (LNT first layer, then ReLU), twin critic on
  ``[s, skill, a]`` with a shared LNT trunk and batched heads, its EMA target, and the update given
  a reward: critic on ``y = r + gamma^n min_k Q_k'(s_{t+n}, a')``, then actor on ``-min_k Q_k``,
  then the target EMA;
* :class:`DDPGModel` -- a pre-trained method: the core and its reward module;
* :class:`IntrinsicDDPGAgent` -- a method's learner = the core trained on one
  :class:`~dvfb.rewards.base.IntrinsicReward` module's reward; a baseline only builds its module;

Their fine-tuner (URLB's) is the registered protocol ``urlb`` (:mod:`dvfb.protocols.urlb`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from dvfb.agents.base import Agent, Model, ReplayNeeds, TrainingSettings, no_skill_like
from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import Actor, TwinCritic, adam, call_network, make_target, soft_update_, training_action, twin_td_loss
from dvfb.nets.execution import NetRunner, PerfConfig, requires_grad_disabled
from dvfb.nets.members import member_mean, minimise
from dvfb.nets.skills import NO_SKILL, SkillSpec
from dvfb.rewards.base import IntrinsicReward

# The CPU-sized preset of the URLB-style agents: the backbone's constants with narrower networks
# and smaller batches, as the FB agents' small preset (docs/results/cpu_experiment.md).
DDPG_SMALL = {"hidden_dim": 256, "batch_size": 256}


@dataclass
class DDPGConfig:
    """The DDPG backbone shared by the URLB-style agents (docs/methods.md, "DDPG core")."""

    hidden_dim: int = param(1024, "Hidden width H of the actor and the critic.", at_least=1)
    batch_size: int = param(1024, "Transitions per gradient update.", at_least=1)
    lr: float = param(1e-4, "Adam learning rate of the actor and the critic.", above=0)
    discount: float = param(0.99, "Discount gamma.", at_least=0, at_most=1)
    nstep: int = param(3, "n of the n-step returns; next_obs of a batch row is s_{t+n}.", at_least=1)
    tau: float = param(0.01, "EMA rate of the target critic (after every update).", above=0, at_most=1)
    stddev: float = param(0.2, "Fixed policy standard deviation sigma.", at_least=0)
    stddev_clip: float = param(0.3, "Noise clip of training samples.", at_least=0)
    fused_adam: bool = param(True, "Use torch's fused Adam where available (same math).")


class DDPGCore(nn.Module):
    """Actor, twin critic and target critic, and one DDPG update given the reward of a batch."""

    generator: torch.Generator | None = None  # the run's stream for the policy noise (None: global)
    members: int = 0  # a group's member count (docs/members.md)

    def __init__(self, obs_dim: int, skill_dim: int, action_dim: int, config: DDPGConfig):
        super().__init__()
        self.config = config
        self.obs_dim, self.skill_dim, self.action_dim = obs_dim, skill_dim, action_dim
        h = config.hidden_dim
        self.actor = Actor(obs_dim, skill_dim, action_dim, h, h, arch="mlp")
        self.critic = self.build_critic()
        self.critic_target = make_target(self.critic)

    def build_critic(self) -> nn.Module:
        """A fresh critic (pre-training, and fine-tuning's new one). Variants of the core (APS's
        successor-feature critic, CeSD's ensemble) override this and :meth:`critic_values`."""
        return TwinCritic(self.obs_dim, self.action_dim, self.skill_dim, self.config.hidden_dim)

    def critic_values(self, critic: nn.Module, obs: torch.Tensor, skill: torch.Tensor, action: torch.Tensor,
                      run=call_network) -> torch.Tensor:
        """The twin Q-values ``(K, N, 1)`` of a critic (the online one or its target)."""
        return run(critic, obs, skill, action)

    def make_optimizers(self) -> None:
        """Fresh Adam optimisers of the actor and the critic (after the core sits on its device)."""
        c = self.config
        self.actor_optimizer = adam(self.actor.parameters(), c.lr, c.fused_adam)
        self.critic_optimizer = adam(self.critic.parameters(), c.lr, c.fused_adam)

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"actor_optimizer": self.actor_optimizer, "critic_optimizer": self.critic_optimizer}

    def critic_loss(self, batch: Batch, skill: torch.Tensor, reward: torch.Tensor, run=call_network) -> torch.Tensor:
        c = self.config
        with torch.no_grad():
            next_action = training_action(run(self.actor, batch.next_obs, skill), c.stddev, c.stddev_clip,
                                          self.generator)
            next_q = self.critic_values(self.critic_target, batch.next_obs, skill, next_action, run).amin(-3)  # (N, 1)
            target = reward + batch.discount * next_q
        return twin_td_loss(self.critic_values(self.critic, batch.obs, skill, batch.action, run), target)

    def actor_loss(self, obs: torch.Tensor, skill: torch.Tensor, run=call_network) -> torch.Tensor:
        c = self.config
        action = training_action(run(self.actor, obs, skill), c.stddev, c.stddev_clip, self.generator)
        return -member_mean(self.critic_values(self.critic, obs, skill, action, run).amin(-3), self.members)

    def update(self, batch: Batch, reward: torch.Tensor, metrics: dict, run=call_network) -> None:
        """Critic step, actor step, target EMA (URLB's order). ``reward`` is ``(N, 1)``."""
        self.train_step(batch, reward, metrics, run)
        self.update_target()

    def update_target(self) -> None:
        soft_update_(self.critic_target, self.critic, self.config.tau)

    def train_step(self, batch: Batch, reward: torch.Tensor, metrics: dict, run=call_network,
                   **critic_options) -> None:
        """Critic step, then actor step; ``critic_options`` go to :meth:`critic_loss` (CeSD's mask)."""
        skill = batch.z if batch.z is not None else no_skill_like(batch.obs)
        critic_loss = self.critic_loss(batch, skill, reward, run, **critic_options)
        minimise(self.critic_optimizer, critic_loss)
        # The critic is differentiated only with respect to the action: its parameters stay out
        # of the actor's graph, and only the actor's leaves receive gradients.
        with requires_grad_disabled(list(self.critic.parameters())):
            actor_loss = self.actor_loss(batch.obs, skill, run)
        minimise(self.actor_optimizer, actor_loss, inputs=list(self.actor.parameters()))
        metrics.update(critic_loss=critic_loss.detach(), actor_loss=actor_loss.detach(),
                       reward=member_mean(reward, self.members))


class DDPGModel(Model):
    """A pre-trained URLB-style agent: the DDPG core (actor, critic, target critic) and its
    intrinsic-reward module, which its snapshots keep (APS's task regression reads its features);
    its skill, if it has one."""

    learns_skill_value = False

    def __init__(self, name: str, obs_dim: int, action_dim: int, skill: SkillSpec, core: DDPGCore,
                 intrinsic: IntrinsicReward, ddpg: DDPGConfig, device: str | torch.device = "cpu",
                 perf: PerfConfig | None = None):
        super().__init__()
        self.name = name
        self.obs_dim, self.action_dim, self.skill = obs_dim, action_dim, skill
        self.settings = TrainingSettings.of(ddpg)
        self.core, self.intrinsic = core, intrinsic
        self.device = torch.device(device)
        self.to(self.device)
        self.net_runner = NetRunner(perf, self.device)

    @property
    def actor(self) -> nn.Module:
        return self.core.actor

    def snapshot_modules(self) -> dict[str, nn.Module]:
        # Everything (URLB pickles the whole agent); fine-tuning uses the actor and the critic.
        return {"core": self.core, "intrinsic": self.intrinsic}


class IntrinsicDDPGAgent(Agent):
    """A URLB-style method's learner: the DDPG core trained on one intrinsic-reward module.

    Subclasses set ``name`` and ``reward_section`` (the run config's section of their reward
    module) and implement :meth:`build_reward`. The run config's ``ddpg`` section configures the
    core. A method with a skill declares it in :meth:`declare_skill` (from its own config section);
    a variant of the core (another critic) sets ``core_cls``; a method whose model does more than
    act (APS's task regression) sets ``model_cls``.
    """

    reward_section: str = ""
    core_cls: type = DDPGCore
    model_cls: type = DDPGModel

    @classmethod
    def from_config(cls, obs_dim, action_dim, config, device="cpu") -> IntrinsicDDPGAgent:
        return cls(obs_dim, action_dim, config.ddpg, getattr(config, cls.reward_section), device, config.perf)

    @classmethod
    def model_from_config(cls, obs_dim, action_dim, config, device="cpu") -> DDPGModel:
        return cls(obs_dim, action_dim, config.ddpg, getattr(config, cls.reward_section), device, config.perf,
                   train=False).model

    def __init__(self, obs_dim: int, action_dim: int, ddpg: DDPGConfig, reward_config,
                 device: str | torch.device = "cpu", perf: PerfConfig | None = None, train: bool = True):
        super().__init__()
        self.ddpg, self.reward_config = ddpg, reward_config
        # What declare_skill, build_core and build_reward read, before the model exists.
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.skill = self.declare_skill()
        core = self.build_core()
        self.adopt(self.model_cls(self.name, obs_dim, action_dim, self.skill, core, self.build_reward(), ddpg,
                                  device, perf))
        if not train:
            return
        self.core.make_optimizers()
        self.intrinsic.make_optimizer(getattr(reward_config, "lr", ddpg.lr), ddpg.fused_adam)
        self.net_runner.compile([self.core.actor, self.core.critic, self.core.critic_target])

    def declare_skill(self) -> SkillSpec:
        """The method's skill (docs/methods.md, "Skills"); the exploration methods have none."""
        return NO_SKILL

    def build_core(self) -> DDPGCore:
        """The core: ``core_cls`` on the ``ddpg`` section (a variant with widths of its own
        section overrides this)."""
        return self.core_cls(self.obs_dim, self.skill.dim, self.action_dim, self.ddpg)

    def build_reward(self) -> IntrinsicReward:
        raise NotImplementedError

    @property
    def actor(self) -> nn.Module:
        return self.core.actor

    @property
    def policy_stddev(self) -> float:
        return self.ddpg.stddev

    def replay_needs(self) -> ReplayNeeds:
        return ReplayNeeds(self.ddpg.batch_size, self.ddpg.discount, nstep=self.ddpg.nstep)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """Train the reward module, score the batch with it, then one DDPG step on that reward."""
        metrics: dict[str, torch.Tensor] = {}
        reward = self.intrinsic.update_and_score(batch, metrics, self.net_runner)
        self.core.update(batch, reward, metrics, self.net_runner)  # logs the reward's mean as "reward"
        return metrics

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opts = self.core.optimizers()
        if self.intrinsic.optimizer is not None:
            opts["reward_optimizer"] = self.intrinsic.optimizer
        return opts

    def pretrained_modules(self) -> dict[str, nn.Module]:
        return self.model.snapshot_modules()
