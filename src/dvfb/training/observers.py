"""Observers of the rollout loop that more than one rollout uses (:mod:`dvfb.training.rollout`):

* :class:`ReplayWriter` -- every lane's steps into its replay (pre-training, fine-tuning and the
  zero-shot protocols' reward-labelled data);
* :class:`EpisodeReturns` -- every lane's episode returns, and success flags where the task has
  them (evaluations, skill selection, the analyses);
* :class:`ProgressCount` -- a progress bar's count, per loop step (frames) or per lane step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from dvfb.training.rollout import Lane, Observer


class ReplayWriter(Observer):
    """Lane ``k``'s steps into ``replays[k]``: the reset observation starts an episode, every step
    adds ``(a, r, discount, s')`` with the lane's skill (``store_skill``; the skill's host copy is
    made once per new skill) and, with ``physics[k]`` (a function returning the environment's
    physics state), the physics state that goes with each observation (docs/methods.md, "Datasets").
    Lanes may leave the rollout (a group's member that stopped): replays follow their lanes."""

    def __init__(self, lanes: list[Lane], replays: Sequence, store_skill: bool = True,
                 physics: Sequence[Callable[[], np.ndarray] | None] | None = None):
        self.lanes, self.store_skill = lanes, store_skill
        physics = physics if physics is not None else [None] * len(replays)
        self.targets = {id(lane): (replay, state) for lane, replay, state in zip(lanes, replays, physics)}

    def episode_started(self, lane: int, obs: np.ndarray) -> None:
        replay, physics = self.targets[id(self.lanes[lane])]
        if physics is None:
            replay.start_episode(obs)
        else:
            replay.start_episode(obs, physics=physics())

    def transition(self, lane: int, step: int, action, reward, discount, next_obs, info) -> None:
        the_lane = self.lanes[lane]
        replay, physics = self.targets[id(the_lane)]
        skill = the_lane.state.skill_host if self.store_skill else None
        if physics is None:
            replay.add(action, reward, discount, next_obs, skill)
        else:
            replay.add(action, reward, discount, next_obs, skill, physics=physics())


class EpisodeReturns(Observer):
    """Each lane's finished episodes: ``returns[k]`` and, where the environment's last ``info`` of
    an episode has a ``success`` flag (Meta-World, docs/tasks.md §4.6), ``successes[k]``; with
    ``skills``, the skill each episode was run with (``skills[k]``)."""

    def __init__(self, lanes: list[Lane], keep_skills: bool = False, accept: Callable[[int], bool] | None = None):
        # accept(step): whether an episode that ends at ``step`` counts (skill selection's rule).
        # ``lanes`` is the rollout's list, which may shrink; results stay at each lane's first position.
        self.lanes, self.keep_skills, self.accept = lanes, keep_skills, accept
        self.position = {id(lane): k for k, lane in enumerate(lanes)}
        self.returns: list[list] = [[] for _ in lanes]
        self.successes: list[list] = [[] for _ in lanes]
        self.skills: list[list] = [[] for _ in lanes]

    def episode_ended(self, lane: int, step: int) -> None:
        if self.accept is not None and not self.accept(step):
            return
        the_lane = self.lanes[lane]
        k = self.position[id(the_lane)]
        self.returns[k].append(the_lane.state.episode_return)
        if "success" in the_lane.last_info:
            self.successes[k].append(bool(the_lane.last_info["success"]))
        if self.keep_skills:
            self.skills[k].append(the_lane.state.skill)


class ProgressCount(Observer):
    """Counts a progress bar (``update(n)``): one per loop step (``per="step"``, frames) or one per
    lane that stepped (``per="transition"``)."""

    def __init__(self, bar, per: str = "step"):
        if per not in ("step", "transition"):
            raise ValueError(f"per must be 'step' or 'transition', got {per!r}")
        self.bar = bar
        if per == "step":
            self.after_step = self._count_step
        else:
            self.transition = self._count_transition

    def _count_step(self, step: int) -> None:
        self.bar.update(1)

    def _count_transition(self, lane: int, step: int, action, reward, discount, next_obs, info) -> None:
        self.bar.update(1)
