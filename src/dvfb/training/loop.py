"""The one training loop of pre-training and fine-tuning, over a data source (docs/methods.md,
"Training loop").

Per step ``t``, whatever the method:

1. the data source prepares the step: the online collector starts an episode when one ended
   (reset, the reset observation into the replay), redraws the rollout skill when the skill rule
   says so, and picks the action (uniform during the uniform phase, else a rollout sample of
   ``pi(s, skill)``);
2. if ``t >= learn_from`` and ``t % update_every == 0``: one update on a batch drawn as the
   learner's :class:`~dvfb.agents.base.ReplayNeeds` say (before stepping, as the authors' code does);
3. the source steps: the environment takes the action and the transition (with its skill) is
   stored;
4. ``after_step(t + 1)`` (logging, snapshots, evaluations), ``after_episode`` at an episode end, then
   the resume checkpoints at episode ends and on signals (:class:`~dvfb.training.checkpointing.ResumeCheckpoints`).

The loop knows no method: it asks its source for transitions, the learner for updates and its hooks
for the rest. A fixed dataset is another source (:class:`DatasetSource`: it steps nothing; the replay holds the data).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dvfb.training.checkpointing import ResumeCheckpoints
from dvfb.training.metrics import MetricWindow, check_action
from dvfb.training.progress import Progress


@dataclass
class EpisodeState:
    """Where the collector stands: what a mid-episode checkpoint keeps."""

    obs: np.ndarray | None = None
    skill: torch.Tensor | None = None
    skill_host: np.ndarray | None = None  # what the replay stores; copied once per new skill
    episode_return: float = 0.0
    episode_start: bool = True
    episode: int = 0

    def set_skill(self, skill: torch.Tensor | None) -> None:
        if skill is not self.skill:
            self.skill = skill
            self.skill_host = None if skill is None else skill.cpu().numpy()


# ``next_skill(step, episode_start, current) -> skill``: the rollout skill of a step.
SkillRule = Callable[[int, bool, "torch.Tensor | None"], "torch.Tensor | None"]


class OnlineCollector:
    """The online data source: acts in an environment and stores every transition in the replay.

    ``uniform(step)`` says whether a step acts uniformly at random (from ``rng``); ``reward_key``
    names the ``info`` field whose reward is stored (pre-training stores the task reward for
    logging, the reward-free update never reads it), None the environment's reward.
    ``first_reset_seed`` seeds the first reset of a fresh run. ``physics`` (the env's
    ``physics_state``), when given, is stored with every observation in the replay's ``physics``
    column (datasets: docs/methods.md, "Datasets").
    """

    def __init__(self, env, replay, agent, rng: np.random.Generator, next_skill: SkillRule,
                 uniform: Callable[[int], bool], *, reward_key: str | None = None,
                 first_reset_seed: int | None = None, state: EpisodeState | None = None,
                 physics: Callable[[], np.ndarray] | None = None):
        self.env, self.replay, self.agent, self.rng = env, replay, agent, rng
        self.next_skill, self.uniform, self.reward_key = next_skill, uniform, reward_key
        self.first_reset_seed = first_reset_seed
        self.physics = physics
        self.state = state if state is not None else EpisodeState()
        self.action_dim = env.action_space.shape[0]
        self.action: np.ndarray | None = None

    def prepare(self, step: int) -> None:
        if self.begin(step):
            self.action = self.uniform_action()
        else:
            self.action = self.agent.act(self.state.obs, self.state.skill, explore=True)

    def uniform_action(self) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)

    def begin(self, step: int) -> bool:
        """Start an episode when one ended and redraw the skill when due; True if the step acts
        uniformly at random (the action is then :meth:`uniform_action`, else the policy's)."""
        s = self.state
        starting = s.episode_start
        if starting:
            if self.first_reset_seed is not None:
                s.obs, _ = self.env.reset(seed=self.first_reset_seed)
                self.first_reset_seed = None
            else:
                s.obs, _ = self.env.reset()
            if self.physics is None:
                self.replay.start_episode(s.obs)
            else:
                self.replay.start_episode(s.obs, physics=self.physics())
            s.episode_return, s.episode_start = 0.0, False
        s.set_skill(self.next_skill(step, starting, s.skill))
        return self.uniform(step)

    def advance(self) -> bool:
        """Step the environment with the prepared action; True at an episode end."""
        s = self.state
        s.obs, reward, terminated, truncated, info = self.env.step(self.action)
        if self.reward_key is not None:
            reward = info[self.reward_key]
        discount = 0.0 if terminated else 1.0
        if self.physics is None:
            self.replay.add(self.action, reward, discount, s.obs, s.skill_host)
        else:
            self.replay.add(self.action, reward, discount, s.obs, s.skill_host, physics=self.physics())
        s.episode_return += reward
        if terminated or truncated:
            s.episode += 1
            s.episode_start = True
            return True
        return False


class DatasetSource:
    """The offline data source: the replay already holds a fixed dataset. A step acts in no
    environment and adds nothing; every step is a boundary at which a checkpoint may be written
    (there is no episode in progress), so checkpoints come every ``checkpoint_every`` steps."""

    def __init__(self):
        self.state = EpisodeState()
        self.action: np.ndarray | None = None

    def prepare(self, step: int) -> None:
        pass

    def advance(self) -> bool:
        return True


class GroupState:
    """Where a group's members stand together: at an episode start only when every member is."""

    def __init__(self, sources: list):
        self.sources = sources

    @property
    def episode_start(self) -> bool:
        return all(source.state.episode_start for source in self.sources)


class GroupSource:
    """The data sources of a group's members (docs/members.md), stepped in lockstep.

    Each member keeps its own environment, replay, random streams and skill rule (its
    :class:`OnlineCollector`, or a :class:`DatasetSource`); the policy's actions of all members
    come from one batched forward of the stacked actor, ``act(obs (M, O), skills) -> (M, U)``.
    ``members()`` lists the live members' sources in stack order (a stopped member leaves it);
    ``on_action_fault(source, message)`` stops a member whose policy produced a non-finite action;
    ``after_episode(source, step)`` runs for each member whose episode ended.
    """

    def __init__(self, members: Callable[[], list], act: Callable, on_action_fault: Callable,
                 after_episode: Callable | None = None):
        self.members, self.act = members, act
        self.on_action_fault, self.after_episode = on_action_fault, after_episode
        self.action = None  # the loop's own action check is per member here
        self.state = GroupState([])

    def prepare(self, step: int) -> None:
        sources = self.members()
        online = [s for s in sources if isinstance(s, OnlineCollector)]
        acting = [s for s in online if not s.begin(step)]
        for s in online:
            if s not in acting:
                s.action = s.uniform_action()
        if acting:
            skills = [s.state.skill for s in acting]
            skill = None if skills[0] is None else torch.stack(skills)
            if len(acting) != len(online):  # the uniform phase is the same steps for every member
                raise RuntimeError("the members of a group left the uniform phase at different steps")
            actions = self.act(np.stack([s.state.obs for s in acting]), skill)
            for s, action in zip(acting, actions):
                s.action = action
            for s in acting:
                if not np.isfinite(s.action).all():
                    self.on_action_fault(s, f"the policy produced a non-finite action at step {step}")

    def advance(self) -> bool:
        sources = self.members()
        for source in sources:
            if source.advance() and self.after_episode is not None and isinstance(source, OnlineCollector):
                self.after_episode(source)
        self.state = GroupState(sources)
        return self.state.episode_start


def run(step: int, total: int, source: OnlineCollector | DatasetSource, update: Callable[[], dict], learn_from: int,
        update_every: int, window: MetricWindow, checkpoints: ResumeCheckpoints, progress: Progress,
        after_step: Callable[[int], None], after_episode: Callable[[int, EpisodeState], None] | None = None) -> int:
    """Run the loop of the module docstring from ``step`` to ``total``; returns the last step.

    ``update()`` samples a batch and makes one update, returning its metric tensors. Use inside
    ``with checkpoints:`` (signals and failures are reported there).
    """
    while step < total:
        source.prepare(step)
        if step >= learn_from and step % update_every == 0:
            window.add(step, update())
        if source.action is not None:
            check_action(source.action, step, window)
        done = source.advance()
        step += 1
        progress.update(1)
        after_step(step)
        if done:
            if after_episode is not None:
                after_episode(step, source.state)
            checkpoints.episode_end(step)
        checkpoints.after_step(step, mid_episode=not source.state.episode_start)
    return step
