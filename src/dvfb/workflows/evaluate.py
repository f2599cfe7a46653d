"""Policy evaluation and reward-labelled data collection (docs/methods.md §8.1, §8.3)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from dvfb.agents import Agent
from dvfb.replay import ReplayBuffer


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
    :class:`~dvfb.workflows.common.Progress`)."""
    return run_episodes(env, lambda obs: agent.act(obs, z, explore=False), episodes, progress)


def collect_inference_data(agent: Agent, env, steps: int, random_action_steps: int,
                           rng: np.random.Generator, max_episode_length: int = 1000, progress=None) -> ReplayBuffer:
    """``steps`` reward-labelled steps in the task (§8.1).

    A new skill from the method's prior at every step; uniform actions for the first
    ``random_action_steps`` steps, then rollout samples of ``pi(s, skill)``.
    """
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    buffer = ReplayBuffer(max(steps, max_episode_length), obs_dim, action_dim, z_dim=0,
                          max_episode_length=max_episode_length, device=agent.device)
    done = True
    obs = None
    for step in range(steps):
        if done:
            obs, _ = env.reset()
            buffer.start_episode(obs)
        z = agent.sample_skill(1)[0]
        if step < random_action_steps:
            action = rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)
        else:
            action = agent.act(obs, z, explore=True)
        obs, reward, terminated, truncated, _ = env.step(action)
        buffer.add(action, reward, 0.0 if terminated else 1.0, obs)
        done = terminated or truncated
        if progress is not None:
            progress.update(1)
    return buffer
