"""The two interfaces between the layers above and every method (docs/methods.md, "The agent
interface"; docs/architecture.md, "A method: model and learner").

A method is a :class:`Model` and a learner (:class:`Agent`):

* the **model** holds what a pre-trained agent is used with -- its networks for acting and for
  zero-shot inference -- and nothing of its training: its skill (:class:`~dvfb.nets.skills.SkillSpec`:
  kind, width, prior, resampling rule) and :meth:`Model.sample_skill`; one batched
  :meth:`Model.act` (``obs (B, O)``, ``skills (B, d)`` -> ``(B, U)``: a rollout sample or the
  mean); the family's inference (:meth:`Model.infer_skill`, :meth:`Model.skill_from_goal`,
  :meth:`Model.regress_skill`, :meth:`Model.skill_value`); and the modules a snapshot loads
  (:meth:`Model.snapshot_modules`). Zero-shot protocols, fine-tuners, ``dvfb.load`` and the analyses
  use models only.
* the **learner** (:class:`Agent`, a :class:`~dvfb.nets.learner.Learner` as every fine-tuner is)
  trains a model without rewards: it owns the model (its networks are registered on the learner
  under their own names, so a learner's state is a flat dict as it always was), the target
  networks, the optimisers and the components a method composes, and :meth:`Agent.update`;
  :meth:`Agent.replay_needs` says how to sample the replay, :meth:`Agent.pretrained_modules` what a
  snapshot keeps, :meth:`Agent.training_state` what a resume checkpoint keeps. Acting and the skill
  are the model's.
* **downstream** -- the method's family chooses the zero-shot protocol and the fine-tuner in its
  :class:`~dvfb.agents.registry.AgentSpec`.
"""


from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from dvfb.core.errors import ConfigError
from dvfb.nets import ACTION_EPS, HostActor, rollout_action
from dvfb.nets.learner import Learner, ReplayNeeds  # noqa: F401  (ReplayNeeds: the methods import it from here)
from dvfb.nets.skills import NO_SKILL, SkillSpec


@dataclass(frozen=True)
class TrainingSettings:
    """What a fine-tuner reuses from the configuration its model was pre-trained with: the widths of a
    fresh critic, the batch, the optimiser and the policy noise (every family's config has them)."""

    hidden_dim: int
    batch_size: int
    lr: float
    fused_adam: bool
    discount: float
    tau: float
    stddev: float
    stddev_clip: float

    @classmethod
    def of(cls, config: Any) -> TrainingSettings:
        """The settings of a family's config section (FBConfig, SFConfig, DDPGConfig)."""
        return cls(**{f: getattr(config, f) for f in cls.__dataclass_fields__})


class Model(nn.Module):
    """Base class of every method's inference model (see the module docstring). Subclasses build
    ``self.actor`` (an :class:`~dvfb.nets.Actor`), set ``skill``, ``settings`` and ``net_runner``
    and implement :meth:`snapshot_modules` and the inference their family has."""

    name: ClassVar[str] = ""
    skill: SkillSpec = NO_SKILL
    # The run's random stream (Model.use_generator); None: torch's global one.
    generator: torch.Generator | None = None
    # 0: an ordinary model; N: a group of N members on stacked tensors (dvfb.nets.members, docs/members.md).
    members: int = 0
    obs_dim: int
    action_dim: int
    device: torch.device
    actor: nn.Module
    settings: TrainingSettings
    net_runner: Any  # dvfb.nets.execution.NetRunner: how its networks execute (precision, compilation)

    # Skills ------------------------------------------------------------------------------------
    @property
    def skill_dim(self) -> int:
        """Width of the skill the actor is conditioned on (and the replay stores); 0 = none."""
        return self.skill.dim

    def sample_skill(self, n: int = 1, generator: torch.Generator | None = None) -> torch.Tensor | None:
        """``n`` draws of the method's skill prior, ``(n, skill_dim)``; None without skills.

        ``generator``: the caller's random stream (None: the model's, see :meth:`use_generator`).
        Methods whose skill kind is ``method`` override this.
        """
        return self.skill.sample(n, self.device, generator if generator is not None else self.generator)

    def use_generator(self, generator: torch.Generator | None) -> None:
        """Draw every random number of this model (skills, policy noise, its modules' samples) from
        ``generator``, the run's own stream, instead of torch's global one."""
        for module in self.modules():
            if hasattr(module, "generator"):
                module.generator = generator

    # Acting ------------------------------------------------------------------------------------
    @property
    def policy_stddev(self) -> float:
        """The fixed standard deviation of rollout actions (§3.3 of docs/methods.md)."""
        return self.settings.stddev

    @torch.inference_mode()
    def act(self, obs: np.ndarray, skills: torch.Tensor | None, explore: bool) -> np.ndarray:
        """Actions for a batch of observations ``obs (B, O)`` with skills ``skills (B, d)`` (None
        without skills): rollout samples if ``explore``, else the means (§3.3); ``(B, U)``.

        An ordinary model acts every row; a group's (docs/members.md) row k is member k's, with its
        own stream's noise. Runs in float32 whatever ``perf`` says (batch 1: per-op overhead, not
        FLOPs). On the CPU every row acts as a separate call at batch 1 does: the mean from
        :class:`~dvfb.nets.HostActor` (numpy on the actor's own parameter storage, several times
        faster than the torch modules at batch 1; bench/README.md), the noise drawn from the row's
        torch stream, so the random stream is the same on every path.
        """
        obs = np.asarray(obs, dtype=np.float32)
        if self.device.type == "cpu":
            return self._act_host(obs, skills, explore)
        return self._act_torch(obs, skills, explore)

    @torch.inference_mode()
    def _act_torch(self, obs: np.ndarray, skills: torch.Tensor | None, explore: bool) -> np.ndarray:
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        if self.members:
            obs_t = obs_t.unsqueeze(1)
            skill_t = skills.unsqueeze(1) if skills is not None else obs_t.new_zeros(obs_t.shape[0], 1, 0)
        else:
            skill_t = skills.reshape(obs_t.shape[0], -1) if skills is not None else obs_t.new_zeros(obs_t.shape[0], 0)
        mean = self.actor(obs_t, skill_t)
        action = rollout_action(mean, self.policy_stddev, self.generator) if explore else mean
        return (action[:, 0] if self.members else action).cpu().numpy()

    def _act_host(self, obs: np.ndarray, skills: torch.Tensor | None, explore: bool) -> np.ndarray:
        rows = obs.shape[0]
        hosts = getattr(self, "_hosts", None)
        count = self.members or 1
        if hosts is None or len(hosts) != count or hosts[0].actor is not self.actor:
            # First call, a new member count, or the actor module was replaced.
            hosts = self._hosts = ([HostActor(self.actor, k) for k in range(self.members)] if self.members
                                   else [HostActor(self.actor)])
        if self.members and rows != self.members:
            raise ValueError(f"a group of {self.members} members acts on {self.members} rows, got {rows}")
        skill_rows = skills.detach().cpu().numpy() if skills is not None else np.zeros((rows, 0), dtype=np.float32)
        generators = self.generator if self.members else [self.generator] * rows
        actions = np.empty((rows, self.action_dim), dtype=np.float32)
        for k in range(rows):
            action = (hosts[k] if self.members else hosts[0])(obs[k], skill_rows[k])
            if explore:
                # rollout_action's math: clamp(mu + sigma * eps), eps ~ N(0, 1) from the row's stream.
                noise = torch.randn(1, self.action_dim, generator=generators[k]).numpy()[0]
                action += noise * np.float32(self.policy_stddev)
                np.minimum(action, np.float32(1 - ACTION_EPS), out=action)
                np.maximum(action, np.float32(-1 + ACTION_EPS), out=action)
            actions[k] = action
        return actions

    # Zero-shot (families that infer a skill from data) ----------------------------------------
    def infer_skill(self, obs: torch.Tensor, next_obs: torch.Tensor, reward: torch.Tensor,
                    inference: Any) -> tuple[torch.Tensor, dict]:
        """The skill of a task from reward-labelled transitions (FB: z_r; SF: a regression)."""
        raise ConfigError(f"agent {self.name!r} does not infer a skill from rewards")

    def skill_from_goal(self, goal_obs: torch.Tensor) -> torch.Tensor:
        """The skill that reaches a goal observation."""
        raise ConfigError(f"agent {self.name!r} does not infer a skill from a goal state")

    def regress_skill(self, obs: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """The skill that best explains rewards of states by the method's own features (APS's
        fine-tuning task regression): a unit vector, or zeros when the rewards give no direction."""
        raise ConfigError(f"agent {self.name!r} has no task regression (--finetune.skill regressed)")

    def goal_widths(self) -> tuple[int, ...]:
        """The sizes a goal given to :meth:`skill_from_goal` may have (first: an observation)."""
        return (self.obs_dim,)

    # Analysis ----------------------------------------------------------------------------------
    learns_skill_value: ClassVar[bool] = False

    def skill_value(self, obs: torch.Tensor, action: torch.Tensor, skill: torch.Tensor,
                    task: torch.Tensor | None = None) -> torch.Tensor:
        """The value of acting with ``skill`` for the task ``task`` (default: the skill's own), ``(N,)``
        (FB: ``Q_M = min_k F_k(s, a, z).z_task``); methods that learn one set ``learns_skill_value``."""
        raise ConfigError(f"agent {self.name!r} has no skill value (only methods that learn one, such as FB and "
                          "DVFB, can be analysed with analyze-value)")

    def nonfinite_hint(self, metric_names: list[str]) -> str:
        """What to tell a user whose update produced these non-finite metrics ("" for nothing)."""
        return ""

    # Snapshots ---------------------------------------------------------------------------------
    def snapshot_modules(self) -> dict[str, nn.Module]:
        """The modules the model loads from a snapshot, under the snapshot's names."""
        raise NotImplementedError

    def load_snapshot(self, modules: dict) -> None:
        """Load the model's modules from a snapshot's state dicts (``snapshot["modules"]``)."""
        for key, module in self.snapshot_modules().items():
            module.load_state_dict(modules[key])

    # Statistics of the pre-training data that a snapshot carries beside the networks, for the
    # protocols that cannot see the replay (task inference from interaction alone reads FB's
    # Cov(B)). Set from the snapshot when the model is loaded (empty for older snapshots).
    statistics: dict[str, torch.Tensor] = {}
    has_statistics: ClassVar[bool] = False  # whether data_statistics computes any

    def data_statistics(self, obs: torch.Tensor, next_obs: torch.Tensor, member: int | None = None
                        ) -> dict[str, torch.Tensor]:
        """The statistics of pre-training transitions ``(n, O)`` a snapshot keeps (``member``: a
        group's member, whose networks are its slice of the stacked ones). None by default."""
        return {}


class Agent(Learner):
    """Base class of every method's learner of pre-training (see the module docstring; the hooks
    it shares with the fine-tuners are :class:`~dvfb.nets.learner.Learner`'s). Subclasses set
    ``name``, build their model and :meth:`adopt` it, and implement :meth:`from_config`,
    :meth:`replay_needs`, :meth:`update`, :meth:`optimizers` and :meth:`pretrained_modules`."""

    name: ClassVar[str] = ""
    model: Model
    # The model's (Agent.adopt copies them): what the layers above read of a learner.
    skill: SkillSpec = NO_SKILL
    obs_dim: int
    action_dim: int
    device: torch.device

    @classmethod
    def from_config(cls, obs_dim: int, action_dim: int, config: Any, device: str | torch.device = "cpu") -> Agent:
        """Build the learner from a run config (its sections and ``perf``)."""
        raise NotImplementedError

    @classmethod
    def model_from_config(cls, obs_dim: int, action_dim: int, config: Any,
                          device: str | torch.device = "cpu") -> Model:
        """Build the method's model alone (no optimiser, no training component): what a snapshot
        is loaded into for zero-shot, fine-tuning and ``dvfb.load``."""
        raise NotImplementedError

    def adopt(self, model: Model) -> None:
        """Own ``model``: its networks become the learner's under their own names (the learner's
        state keeps its flat keys), the model itself is not a sub-module (no key twice); its skill,
        dimensions and device are the learner's (its random stream and runner are read from it)."""
        object.__setattr__(self, "model", model)
        for name, module in model.named_children():
            self.add_module(name, module)
        self.skill, self.obs_dim, self.action_dim = model.skill, model.obs_dim, model.action_dim
        self.device = model.device

    @property
    def skill_dim(self) -> int:
        return self.skill.dim

    def sample_skill(self, n: int = 1, generator: torch.Generator | None = None) -> torch.Tensor | None:
        return self.model.sample_skill(n, generator)

    def explore_skill(self, obs: np.ndarray, generator: torch.Generator | None = None,
                      member: int | None = None) -> torch.Tensor | None:
        """The skill pre-training acts with from ``obs`` until the skill rule redraws it (docs/methods.md,
        "Skills"): a draw of the prior, unless the method chooses it from the state (FBEE).
        ``member``: a group's member whose rollout it is (its networks are its slice)."""
        return self.sample_skill(1, generator=generator)[0]

    def pretrained_modules(self) -> dict[str, nn.Module]:
        """What a snapshot keeps (the model's modules, and what else the method's snapshots hold)."""
        raise NotImplementedError


def no_skill_like(obs: torch.Tensor) -> torch.Tensor:
    """An empty ``(N, 0)`` skill (a group's: ``(M, N, 0)``), so that skill-less methods share the
    skill-conditioned networks."""
    return obs.new_zeros(*obs.shape[:-1], 0)
