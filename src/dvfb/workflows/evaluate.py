"""Policy evaluation and reward-labelled data collection (docs/methods.md §8.1, §8.3)."""

from __future__ import annotations

import numpy as np
import torch

from dvfb.agents import Agent
from dvfb.replay import ReplayBuffer


def evaluate_policy(agent: Agent, env, z: torch.Tensor | None, episodes: int, progress=None) -> list[float]:
    """Undiscounted returns of ``episodes`` mean-action episodes with a fixed skill z (§8.3), or
    without one for methods that have none (``z = None``). ``progress.update(1)`` is called per
    step when given (a :class:`~dvfb.workflows.common.Progress`)."""
    returns = []
    for _ in range(episodes):
        obs, _ = env.reset()
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, z, explore=False))
            total += reward
            if progress is not None:
                progress.update(1)
            done = terminated or truncated
        returns.append(total)
    return returns


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
