"""URLB's fine-tuning of the DDPG-core methods (docs/methods.md, "Fine-tuning the URLB-style agents").

The pre-trained actor is kept; the critic is fresh (the core's own :meth:`build_critic`, so APS's
successor-feature critic and CeSD's ensemble are rebuilt as themselves), with its trunk
(``init_critic="trunk"``) or all of it (``"all"``, Proto) copied from pre-training. The target
critic is the copy of the *fresh* critic made before the trunk copy and is never re-synchronised
(URLB's behaviour; it drifts to the trained one by the EMA). Optimisers are new; the intrinsic
module is no longer used; the reward is the extrinsic n-step sum.

The rollout skill of a method with skills (docs/methods.md, "Fine-tuning the URLB-style agents"):

* ``selected`` (the paper's protocol, default) -- the skill the zero-shot protocol selected, fixed;
* ``resample`` (the DVFB authors' driver for DIAYN, APS, SMM and CeSD) -- redrawn from the prior by
  the method's pre-training rule;
* ``random_fixed`` (BeCL's and the official CeSD driver) -- one prior draw, fixed for the run;
* ``prior_mean`` (CIC's fine-tuning skill, 0.5 in every coordinate) -- the mean of a box prior;
* ``regressed`` (URLB's APS) -- after ``regress_after`` steps and then whenever the skill rule's
  period comes round, the method's task regression on ``regress_samples`` tuples of the fine-tuning
  replay (their ``s_t`` and n-step rewards) gives the skill; the selected one before.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from dvfb.agents.base import ReplayNeeds
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import make_target
from dvfb.protocols.base import Finetuner, FinetuneSchedule, register_finetuner

CRITIC_INITS = ("trunk", "all", "none")
FINETUNE_SKILLS = ("selected", "resample", "random_fixed", "prior_mean", "regressed")


@dataclass
class DDPGFinetuneConfig(FinetuneSchedule):
    """URLB-style fine-tuning (docs/methods.md, "Fine-tuning the URLB-style agents")."""

    init_critic: str = param("trunk", "What the fresh critic copies from pre-training: its trunk (URLB), all of "
                             "it (Proto), or nothing.", CRITIC_INITS)
    skill: str = param("selected", "Methods with skills: the selected skill, fixed (paper); resampled by the "
                       "pre-training rule; one random prior draw, fixed; the mean of a box prior (CIC's "
                       "0.5); or regressed from the replay's rewards (URLB's APS). The inference steps that select a skill are not counted in --finetune.frames.",
                       FINETUNE_SKILLS)
    regress_after: int = param(4096, "--finetune.skill regressed: steps before the first task regression "
                               "(URLB's num_init_steps).", at_least=1)
    regress_samples: int = param(4096, "--finetune.skill regressed: replay tuples per regression (URLB's "
                                 "lstsq_batch_size).", at_least=1)


@register_finetuner
class DDPGFinetuner(Finetuner):
    """Fine-tune a URLB-style agent on the extrinsic n-step reward (see the module docstring)."""

    name = "urlb"
    config_cls = DDPGFinetuneConfig
    uniform_seed_actions = True

    def __init__(self, model, skill: torch.Tensor | None, config: DDPGFinetuneConfig):
        super().__init__(model, skill, config)
        core = model.core
        fresh = core.build_critic().to(model.device)
        target = make_target(fresh)
        if config.init_critic == "trunk":
            fresh.trunk.load_state_dict(core.critic.trunk.state_dict())
        elif config.init_critic == "all":
            fresh.load_state_dict(core.critic.state_dict())
        core.critic, core.critic_target = fresh, target
        core.make_optimizers()
        spec = model.skill
        self.check(model, config)
        if spec.has_skill and config.skill == "prior_mean":
            self.skill = torch.full((spec.dim,), (spec.low + spec.high) / 2, device=model.device)
        elif spec.has_skill and config.skill == "random_fixed":
            self.skill = model.sample_skill(1)[0]
        self.replay = None

    @classmethod
    def check(cls, model, config: DDPGFinetuneConfig) -> None:
        spec = model.skill
        if spec.has_skill and config.skill == "prior_mean" and spec.kind != "box":
            raise ConfigError(f"--finetune.skill prior_mean needs a box prior; {model.name!r} has a {spec.kind} skill")
        if spec.has_skill and config.skill == "regressed":
            model.regress_skill(torch.zeros(1, model.obs_dim, device=model.device),
                                torch.ones(1, 1, device=model.device))  # its one-line error if it has none

    def update_networks(self) -> list[nn.Module]:
        core = self.model.core
        return [core.actor, core.critic, core.critic_target]

    @classmethod
    def check_group(cls, config: DDPGFinetuneConfig) -> None:
        if config.skill == "regressed":
            raise ConfigError("--finetune.skill regressed fits each run's skill to its own fine-tuning replay as it "
                              "goes; fine-tune these runs one at a time")

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return self.model.core.optimizers()

    def bind_replay(self, replay) -> None:
        self.replay = replay

    def rollout_skill(self, step, episode_start, current, generator=None, obs=None):
        spec, c = self.model.skill, self.config
        if c.skill == "resample" and spec.has_skill:
            if current is None or spec.due(step, episode_start):
                return self.model.sample_skill(1, generator=generator)[0]
            return current
        if c.skill == "regressed" and spec.has_skill and step >= c.regress_after and spec.due(step, episode_start):
            ddpg = self.model.core.config
            batch = ReplayNeeds(c.regress_samples, ddpg.discount, nstep=ddpg.nstep).sample(self.replay)
            task = self.model.regress_skill(batch.obs, batch.reward)  # a unit vector, or 0: no direction
            # Rewards with no direction (all zero so far, as sparse tasks start) keep the skill;
            # torch.where, not an if: no host sync. Evaluations use the regressed skill.
            self.skill = torch.where(task.norm() > 0.5, task, self.skill)
        return self.skill

    @classmethod
    def needs_of(cls, model) -> ReplayNeeds:
        # The core's own batches: a method that asks for more rows in pre-training (BeCL's fresh
        # batch per contrastive step) trains only its core here.
        ddpg = model.core.config
        return ReplayNeeds(ddpg.batch_size, ddpg.discount, nstep=ddpg.nstep)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        metrics: dict[str, torch.Tensor] = {}
        self.model.core.update(batch, batch.reward, metrics, self.net_runner)
        return metrics

    def training_state(self) -> dict:
        core = self.model.core
        return {"core": core.state_dict(), "optimizers": {k: o.state_dict() for k, o in core.optimizers().items()},
                "skill": None if self.skill is None else self.skill.cpu()}

    def load_training_state(self, state: dict) -> None:
        core = self.model.core
        core.load_state_dict(state["core"])
        for k, o in core.optimizers().items():
            o.load_state_dict(state["optimizers"][k])
        if state.get("skill") is not None:
            self.skill = state["skill"].to(self.model.device)
