"""The one interface between the workflows and every method (docs/methods.md, "The agent interface").

A workflow (pre-training, zero-shot, fine-tuning, the analyses) sees an agent only through
:class:`Agent`:

* **skills** -- ``skill``, the method's :class:`~dvfb.skills.SkillSpec` (kind, width, prior,
  resampling rule); :meth:`Agent.sample_skill` draws from the prior; the training loop redraws
  when ``skill.due(step, episode_start)`` says so;
* **acting** -- :meth:`Agent.act` for one observation and an optional skill, a rollout sample or
  the mean;
* **learning** -- :meth:`Agent.replay_needs` says how to sample the replay (batch size, discount,
  n-step, whether ``s_{t+2}`` is needed), :meth:`Agent.update` takes one batch and returns
  detached metric tensors;
* **state** -- :meth:`Agent.pretrained_modules` (what a snapshot keeps),
  :meth:`Agent.training_state` / :meth:`Agent.load_training_state` (networks, statistics and
  optimisers, for exact resume);
* **downstream** -- the method's family chooses the zero-shot strategy and the fine-tuner in its
  :class:`~dvfb.agents.registry.AgentSpec`; families that infer a skill from reward-labelled data
  implement :meth:`Agent.infer_skill` (and :meth:`Agent.skill_from_goal` where it makes sense).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from dvfb.errors import ConfigError
from dvfb.nets import ACTION_EPS, HostActor, rollout_action
from dvfb.data import Batch
from dvfb.skills import NO_SKILL, SkillSpec


@dataclass(frozen=True)
class ReplayNeeds:
    """How an agent's batches are drawn from the replay buffer (docs/methods.md, "Replay").

    ``nstep``: rewards summed over n steps with ``discount = gamma^n`` and ``next_obs = s_{t+n}``,
    never across an episode boundary (n = 3 for the URLB-style agents). ``need_future``: the batch
    also carries ``s_{t+2}`` (FB's ``code_exact`` pairings).
    """

    batch_size: int
    discount: float
    nstep: int = 1
    need_future: bool = False

    def sample(self, replay, generator: torch.Generator | None = None) -> Batch:
        return replay.sample(self.batch_size, self.discount, need_future=self.need_future, nstep=self.nstep,
                             generator=generator)


class Agent(nn.Module):
    """Base class of every method. Subclasses set ``name``, build ``self.actor`` (an
    :class:`~dvfb.nets.Actor`) and implement :meth:`from_config`, :meth:`replay_needs`,
    :meth:`update`, :meth:`optimizers` and :meth:`pretrained_modules`."""

    name: ClassVar[str] = ""
    skill: SkillSpec = NO_SKILL
    # The run's random stream (Agent.use_generator); None: torch's global one.
    generator: torch.Generator | None = None
    # 0: an ordinary agent; N: a group of N members on stacked tensors (dvfb.nets.members, docs/members.md).
    members: int = 0
    obs_dim: int
    action_dim: int
    device: torch.device
    actor: nn.Module

    @classmethod
    def from_config(cls, obs_dim: int, action_dim: int, config: Any, device: str | torch.device = "cpu") -> Agent:
        """Build the agent from a run config (its sections and ``perf``)."""
        raise NotImplementedError

    # Skills ------------------------------------------------------------------------------------
    @property
    def skill_dim(self) -> int:
        """Width of the skill the actor is conditioned on (and the replay stores); 0 = none."""
        return self.skill.dim

    def sample_skill(self, n: int = 1, generator: torch.Generator | None = None) -> torch.Tensor | None:
        """``n`` draws of the method's skill prior, ``(n, skill_dim)``; None without skills.

        ``generator``: the caller's random stream (None: the agent's, see :meth:`use_generator`).
        Methods whose skill kind is ``method`` override this.
        """
        return self.skill.sample(n, self.device, generator if generator is not None else self.generator)

    def use_generator(self, generator: torch.Generator | None) -> None:
        """Draw every random number of this agent (skills, policy noise, the modules' samples) from
        ``generator``, the run's own stream, instead of torch's global one."""
        for module in self.modules():
            if hasattr(module, "generator"):
                module.generator = generator

    # Learning ----------------------------------------------------------------------------------
    def replay_needs(self) -> ReplayNeeds:
        raise NotImplementedError

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    # Acting ------------------------------------------------------------------------------------
    @property
    def policy_stddev(self) -> float:
        """The fixed standard deviation of rollout actions (§3.3 of docs/methods.md)."""
        raise NotImplementedError

    def act(self, obs: np.ndarray, skill: torch.Tensor | None, explore: bool) -> np.ndarray:
        """One action for one observation: a rollout sample if ``explore``, else the mean (§3.3).

        Runs in float32 whatever ``perf`` says (batch 1: per-op overhead, not FLOPs). On the CPU
        the mean comes from :class:`~dvfb.nets.HostActor` (numpy on the actor's own parameter
        storage, several times faster than the torch modules at batch 1; bench/README.md); the
        exploration noise is still drawn from torch's generator, so the random stream is the same
        on every path.
        """
        if self.device.type != "cpu":
            return self._act_torch(obs, skill, explore)
        host = getattr(self, "_host_actor", None)
        if host is None or host.actor is not self.actor:
            host = self._host_actor = HostActor(self.actor)  # first call, or the actor module was replaced
        skill_np = skill.detach().numpy() if skill is not None else np.zeros(0, dtype=np.float32)
        action = host(obs, skill_np)
        if explore:
            # rollout_action's math: clamp(mu + sigma * eps), eps ~ N(0, 1) from torch's stream.
            action += torch.randn(1, self.action_dim, generator=self.generator).numpy()[0] * np.float32(self.policy_stddev)
            np.minimum(action, np.float32(1 - ACTION_EPS), out=action)
            np.maximum(action, np.float32(-1 + ACTION_EPS), out=action)
        return action

    @torch.inference_mode()
    def act_members(self, obs: np.ndarray, skill: torch.Tensor | None, explore: bool) -> np.ndarray:
        """A group's actions (docs/members.md): member k's for its observation ``obs[k]`` and skill
        ``skill[k]``, ``(M, action_dim)``, from one batched actor forward; member k's exploration
        noise comes from its own stream, as its separate run's :meth:`act` draws it."""
        if self.device.type == "cpu":
            return self._act_members_host(obs, skill, explore)
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(1)
        skill_t = skill.unsqueeze(1) if skill is not None else obs_t.new_zeros(obs_t.shape[0], 1, 0)
        mean = self.actor(obs_t, skill_t)
        action = rollout_action(mean, self.policy_stddev, self.generator) if explore else mean
        return action[:, 0].cpu().numpy()

    def _act_members_host(self, obs: np.ndarray, skill: torch.Tensor | None, explore: bool) -> np.ndarray:
        # On the CPU each member acts as its separate run does (HostActor on its slice of the
        # stacked actor, noise from its stream): at batch 1 numpy beats any batched torch call.
        hosts = getattr(self, "_member_hosts", None)
        if hosts is None or len(hosts) != self.members or hosts[0].actor is not self.actor:
            hosts = self._member_hosts = [HostActor(self.actor, k) for k in range(self.members)]
        skills = skill.detach().numpy() if skill is not None else np.zeros((len(hosts), 0), dtype=np.float32)
        actions = np.stack([host(o, z) for host, o, z in zip(hosts, obs, skills)])
        if explore:
            for action, generator in zip(actions, self.generator):
                action += torch.randn(1, self.action_dim, generator=generator).numpy()[0] * np.float32(self.policy_stddev)
                np.minimum(action, np.float32(1 - ACTION_EPS), out=action)
                np.maximum(action, np.float32(-1 + ACTION_EPS), out=action)
        return actions

    @torch.inference_mode()
    def _act_torch(self, obs: np.ndarray, skill: torch.Tensor | None, explore: bool) -> np.ndarray:
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        skill_t = skill.reshape(1, -1) if skill is not None else obs_t.new_zeros(1, 0)
        mean = self.actor(obs_t, skill_t)
        action = rollout_action(mean, self.policy_stddev, self.generator) if explore else mean
        return action[0].cpu().numpy()

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

    # State -------------------------------------------------------------------------------------
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def pretrained_modules(self) -> dict[str, nn.Module]:
        """What a snapshot keeps and zero-shot / fine-tuning load."""
        raise NotImplementedError

    def training_state(self) -> dict:
        """Networks, running statistics and optimiser states (for resume)."""
        return {"modules": self.state_dict(),
                "optimizers": {k: o.state_dict() for k, o in self.optimizers().items()}}

    def load_training_state(self, state: dict) -> None:
        self.load_state_dict(state["modules"])
        for k, o in self.optimizers().items():
            o.load_state_dict(state["optimizers"][k])


def no_skill_like(obs: torch.Tensor) -> torch.Tensor:
    """An empty ``(N, 0)`` skill (a group's: ``(M, N, 0)``), so that skill-less methods share the
    skill-conditioned networks."""
    return obs.new_zeros(*obs.shape[:-1], 0)
