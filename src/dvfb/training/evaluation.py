"""Evaluation episodes (docs/methods.md §8.3): mean actions with a fixed skill, as rollouts of the one
loop (:mod:`dvfb.training.rollout`). The protocols find the skill; this runs it."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch

from dvfb.training.observers import EpisodeReturns, ProgressCount
from dvfb.training.rollout import Lane, Policy, rollout


@dataclasses.dataclass
class Evaluation:
    """The outcome of evaluation episodes.

    Attributes:
        returns: the undiscounted return of each episode.
        successes: for tasks with a success criterion (Meta-World), whether each episode was a
            success at its final step (docs/tasks.md §4.6); None for tasks without one.
    """

    returns: list[float]
    successes: list[bool] | None = None

    def summary(self) -> dict:
        """``mean_return``, ``std_return``, ``returns`` and, with successes, ``success_rate`` and
        ``successes``: the fields every result file and curve point carries."""
        out = {"mean_return": float(np.mean(self.returns)) if self.returns else float("nan"),
               "std_return": float(np.std(self.returns)) if self.returns else float("nan"),
               "returns": self.returns}
        if self.successes is not None:
            out["success_rate"] = float(np.mean(self.successes)) if self.successes else float("nan")
            out["successes"] = self.successes
        return out


def evaluations(recorder: EpisodeReturns) -> list[Evaluation]:
    """One :class:`Evaluation` per lane of what ``recorder`` saw (successes where every episode had one)."""
    return [Evaluation(r, s if len(s) == len(r) and s else None)
            for r, s in zip(recorder.returns, recorder.successes)]


def run_episodes(lanes: list[Lane], policy: Policy, episodes: int, progress=None) -> list[Evaluation]:
    """``episodes`` episodes of every lane, started together, with ``policy``; one
    :class:`Evaluation` per lane. ``progress.update(1)`` is called per lane step when given (a
    :class:`~dvfb.training.progress.Progress`)."""
    recorder = EpisodeReturns(lanes)
    observers = [recorder] + ([ProgressCount(progress, per="transition")] if progress is not None else [])
    rollout(lanes, policy, observers, episodes=episodes)
    return evaluations(recorder)


def evaluate(act: Callable[[np.ndarray, torch.Tensor | None, bool], np.ndarray], envs: Sequence,
             skills: Sequence[torch.Tensor | None], episodes: int, progress=None) -> list[Evaluation]:
    """``episodes`` mean-action episodes per environment (§8.3): ``envs[k]`` with the fixed skill
    ``skills[k]`` (None for methods without one), all in lockstep, the actions from one batched
    ``act(obs (B, O), skills (B, d), explore)`` per step (a model's, or a group's: row k is member k)."""
    lanes = [Lane(env) for env in envs]
    for lane, skill in zip(lanes, skills):
        lane.state.set_skill(skill)
    return run_episodes(lanes, Policy(lambda obs, skill: act(obs, skill, False)), episodes, progress)


def run_episode(env, act: Callable[[np.ndarray, torch.Tensor | None, bool], np.ndarray], skill: torch.Tensor | None,
                explore: bool = False, observers: Sequence = (), max_steps: int | None = None,
                reset_seed: int | None = None) -> Lane:
    """One episode of ``env`` (at most ``max_steps`` steps) with the fixed ``skill``, watched by
    ``observers``; its lane (``lane.state.episode_return``: the return of the steps taken)."""
    lane = Lane(env, reset_seed=reset_seed)
    lane.state.set_skill(skill)
    rollout([lane], Policy(lambda obs, skills: act(obs, skills, explore)), observers, stop=max_steps, episodes=1)
    return lane
