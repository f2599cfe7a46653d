"""The one rollout loop: every environment step dvfb takes goes through :func:`rollout`
(docs/architecture.md, "The rollout loop").

Pre-training's and fine-tuning's collection, the zero-shot protocols' data collection and skill
selection, evaluations, videos and the rollout analyses are policies and observers of it. A rollout
steps one or more *lanes* in lockstep (a :class:`Lane` is an environment and the episode it is in:
one for a run, one per member for a group, docs/members.md) with a :class:`Policy` that gives every
lane's action in one batched call, and :class:`Observer` s that record what happens.

Per step ``t`` (``step`` counts the loop's steps, the frames of a lane):

1. every lane whose episode ended starts one (reset; :meth:`Observer.episode_started`), then the
   policy's skill rule gives each lane its skill for the step (a new draw when the rule says so);
2. the policy gives the actions: uniform from each lane's ``rng`` in the uniform phase, else one
   batched ``act(obs (B, O), skills (B, d))``; :meth:`Policy.check` may stop a lane whose action is
   not finite (a group's member) or end the rollout;
3. :meth:`Observer.before_env_step` (the training loop's update, which the authors' code makes
   before stepping);
4. every lane steps its environment (:meth:`Observer.transition` with the step's reward and
   ``info``);
5. ``t + 1``: :meth:`Observer.after_step` (logging, snapshots, evaluations, progress), then
   :meth:`Observer.episode_ended` for each lane whose episode ended, then
   :meth:`Observer.step_done` with whether every lane stands at an episode boundary (resume
   checkpoints).

The loop ends at ``stop`` steps, or, with ``episodes``, once every lane has finished that many:
lanes then start their episodes together and a lane whose episode ended waits (it is not stepped)
until the others' end (evaluations of a group). A rollout with no lane (offline training) steps no
environment: every step is an episode boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass
class EpisodeState:
    """Where a lane stands: what a mid-episode checkpoint keeps."""

    obs: np.ndarray | None = None
    skill: torch.Tensor | None = None
    skill_host: np.ndarray | None = None  # what a replay stores; copied once per new skill
    episode_return: float = 0.0
    episode_start: bool = True
    episode: int = 0

    def set_skill(self, skill: torch.Tensor | None) -> None:
        if skill is not self.skill:
            self.skill = skill
            self.skill_host = None if skill is None else skill.cpu().numpy()


class Lane:
    """One environment of a rollout and the episode it is in.

    ``rng`` draws its uniform actions; ``reset_seed`` seeds its next reset (a fresh run's first);
    ``reward_key`` names the ``info`` field whose reward the lane records (pre-training records the
    domain task's reward for logging), None the environment's reward.
    """

    def __init__(self, env, rng: np.random.Generator | None = None, state: EpisodeState | None = None,
                 reset_seed: int | None = None, reward_key: str | None = None):
        self.env, self.rng, self.reset_seed, self.reward_key = env, rng, reset_seed, reward_key
        self.state = state if state is not None else EpisodeState()
        self.action_dim = env.action_space.shape[0]
        self.last_info: dict = {}

    def reset(self) -> np.ndarray:
        if self.reset_seed is not None:
            obs, info = self.env.reset(seed=self.reset_seed)
            self.reset_seed = None
        else:
            obs, info = self.env.reset()
        state = self.state
        state.obs, state.episode_return, state.episode_start = obs, 0.0, False
        self.last_info = info
        return obs

    def uniform_action(self) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)


# ``rule(step, episode_start, current) -> skill``: a lane's skill for a step.
SkillRule = Callable[[int, bool, "torch.Tensor | None"], "torch.Tensor | None"]


class Policy:
    """How a rollout acts.

    ``act(obs (B, O), skills (B, d) | None) -> (B, U)`` gives every lane's action in one call (a
    model's batched act); ``skill_rules`` gives each lane's skill rule (None: the lane keeps the skill
    it has); ``uniform(step)`` says whether a step acts uniformly at random (from each lane's
    ``rng``). A subclass may override :meth:`check` to stop lanes whose action is not finite.
    """

    def __init__(self, act: Callable[[np.ndarray, torch.Tensor | None], np.ndarray],
                 skill_rules: Sequence[SkillRule | None] | None = None,
                 uniform: Callable[[int], bool] | None = None):
        self.act, self.skill_rules, self.uniform = act, skill_rules, uniform

    def choose_skills(self, step: int, lanes: Sequence[Lane], starting: Sequence[bool]) -> None:
        if self.skill_rules is None:
            return
        for lane, rule, start in zip(lanes, self.skill_rules, starting):
            if rule is not None:
                lane.state.set_skill(rule(step, start, lane.state.skill))

    def actions(self, step: int, lanes: Sequence[Lane]) -> list[np.ndarray]:
        if self.uniform is not None and self.uniform(step):
            return [lane.uniform_action() for lane in lanes]
        if len(lanes) == 1:
            # One lane (an ordinary run): views instead of stacked copies, once per step.
            state = lanes[0].state
            skill = None if state.skill is None else state.skill.unsqueeze(0)
            return list(self.act(np.asarray(state.obs)[None], skill))
        skills = [lane.state.skill for lane in lanes]
        skill = None if skills[0] is None else torch.stack(skills)
        return list(self.act(np.stack([lane.state.obs for lane in lanes]), skill))

    def check(self, step: int, lanes: list[Lane], actions: list[np.ndarray]) -> list[np.ndarray]:
        """The actions the lanes step with; may remove lanes (and their actions) from ``lanes``."""
        return actions


class Observer:
    """What watches a rollout; every hook is optional (these do nothing). ``lane`` is the lane's
    index in the rollout's list of lanes."""

    def episode_started(self, lane: int, obs: np.ndarray) -> None:
        """Lane ``lane`` was reset to ``obs``."""

    def before_env_step(self, step: int) -> None:
        """The actions of step ``step`` are chosen; the environments have not stepped yet."""

    def transition(self, lane: int, step: int, action: np.ndarray, reward: float, discount: float,
                   next_obs: np.ndarray, info: dict) -> None:
        """Lane ``lane`` took ``action`` at step ``step``."""

    def after_step(self, step: int) -> None:
        """``step`` steps are done."""

    def episode_ended(self, lane: int, step: int) -> None:
        """Lane ``lane``'s episode ended with the step that made ``step`` steps."""

    def step_done(self, step: int, boundary: bool) -> None:
        """The last hook of a step; ``boundary``: every lane stands at an episode boundary."""


_HOOKS = ("episode_started", "before_env_step", "transition", "after_step", "episode_ended", "step_done")


def _hooks(observers: Sequence[Any]) -> dict[str, list[Callable]]:
    """Each hook's bound methods, of the observers that define it (any object may observe)."""
    found: dict[str, list[Callable]] = {name: [] for name in _HOOKS}
    for observer in observers:
        for name in _HOOKS:
            method = getattr(observer, name, None)
            if method is None or getattr(method, "__func__", method) is getattr(Observer, name):
                continue  # absent, or the base class's no-op
            found[name].append(method)
    return found


def rollout(lanes: list[Lane], policy: Policy | None, observers: Sequence[Any] = (), *, start: int = 0,
            stop: int | None = None, episodes: int | None = None) -> int:
    """Run the loop of the module docstring from step ``start``; returns the step it ended at.

    ``lanes`` may shrink while it runs (:meth:`Policy.check`: a group's member that stopped).
    """
    if stop is None and episodes is None:
        raise ValueError("a rollout needs stop steps or a number of episodes")
    hooks = _hooks(observers)
    started, before, transition = hooks["episode_started"], hooks["before_env_step"], hooks["transition"]
    after, ended_hooks, done_hooks = hooks["after_step"], hooks["episode_ended"], hooks["step_done"]
    rounds = 0
    step = start
    while stop is None or step < stop:
        if episodes is not None and all(lane.state.episode_start for lane in lanes):
            if rounds == episodes:
                break
            rounds += 1
            stepping = list(lanes)
        elif episodes is not None:
            stepping = [lane for lane in lanes if not lane.state.episode_start]  # the others wait
        else:
            stepping = lanes
        starting = [lane.state.episode_start for lane in lanes]
        for index, (lane, start_now) in enumerate(zip(lanes, starting)):
            if start_now and lane in stepping:
                obs = lane.reset()
                for hook in started:
                    hook(index, obs)
        if policy is not None:
            policy.choose_skills(step, lanes, starting)
        if lanes:
            actions = policy.check(step, lanes, policy.actions(step, lanes))
            if episodes is not None:
                stepping = [lane for lane in stepping if lane in lanes]
        for hook in before:
            hook(step)
        ended = []
        for index, (lane, action) in enumerate(zip(lanes, actions) if lanes else ()):
            if lane not in stepping:
                continue
            state = lane.state
            obs, reward, terminated, truncated, info = lane.env.step(action)
            if lane.reward_key is not None:
                reward = info[lane.reward_key]
            discount = 0.0 if terminated else 1.0
            state.obs = obs
            state.episode_return += reward
            lane.last_info = info
            for hook in transition:
                hook(index, step, action, reward, discount, obs, info)
            if terminated or truncated:
                state.episode += 1
                state.episode_start = True
                ended.append(index)
        step += 1
        for hook in after:
            hook(step)
        for index in ended:
            for hook in ended_hooks:
                hook(index, step)
        if done_hooks:
            boundary = all(lane.state.episode_start for lane in lanes)
            for hook in done_hooks:
                hook(step, boundary)
    return step
