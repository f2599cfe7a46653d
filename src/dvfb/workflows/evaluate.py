"""Policy evaluation (docs/methods.md §8.3); the protocols collect their own task data."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from dvfb.agents import Agent


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


def run_episodes(env, policy, episodes: int, progress=None) -> Evaluation:
    """Run ``episodes`` episodes of ``policy(obs) -> action``; success is read at the final step."""
    returns, successes = [], []
    for _ in range(episodes):
        obs, _ = env.reset()
        total, done, info = 0.0, False, {}
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            total += reward
            if progress is not None:
                progress.update(1)
            done = terminated or truncated
        returns.append(total)
        if "success" in info:
            successes.append(bool(info["success"]))
    return Evaluation(returns, successes if len(successes) == len(returns) and successes else None)


def evaluate_policy(agent: Agent, env, z: torch.Tensor | None, episodes: int, progress=None) -> Evaluation:
    """``episodes`` mean-action episodes with a fixed skill z (§8.3), or without one for methods
    that have none (``z = None``). ``progress.update(1)`` is called per step when given (a
    :class:`~dvfb.training.progress.Progress`)."""
    return run_episodes(env, lambda obs: agent.act(obs, z, explore=False), episodes, progress)


def evaluate_group(group: Agent, envs: list, skills: torch.Tensor | None, episodes: int,
                   progress=None) -> list[Evaluation]:
    """:func:`evaluate_policy` of every member of a stacked group (docs/members.md): member k's
    episodes in ``envs[k]`` with its skill ``skills[k]``, all members in lockstep, their mean actions
    from one batched forward per step."""
    m = len(envs)
    returns = [[] for _ in range(m)]
    successes = [[] for _ in range(m)]
    for _ in range(episodes):
        obs = [env.reset()[0] for env in envs]
        totals, done, infos = [0.0] * m, [False] * m, [{}] * m
        while not all(done):
            actions = group.act_members(np.stack(obs), skills, explore=False)
            for k, env in enumerate(envs):
                if done[k]:
                    continue
                obs[k], reward, terminated, truncated, infos[k] = env.step(actions[k])
                totals[k] += reward
                done[k] = terminated or truncated
                if progress is not None:
                    progress.update(1)
        for k in range(m):
            returns[k].append(totals[k])
            if "success" in infos[k]:
                successes[k].append(bool(infos[k]["success"]))
    return [Evaluation(r, s if len(s) == len(r) and s else None) for r, s in zip(returns, successes)]
