"""``make``: build a task's gymnasium environment by name (docs/tasks.md §3, §5)."""

from __future__ import annotations

import gymnasium as gym

from dvfb.envs.gym_env import DMCGymEnv
from dvfb.envs.registry import check_domain, domain_module, resolve_task


def make(
    name: str,
    seed: int | None = None,
    reward_free: bool = False,
    render_mode: str | None = None,
) -> gym.Env:
    """Build the gymnasium environment of a task.

    Args:
        name: a full task name such as ``walker_flip`` (see ``dvfb.envs.TASKS``); with
            ``reward_free=True`` a bare domain name (``walker``) is also accepted and means the
            domain's pre-training task (docs/tasks.md §5).
        seed: seeds the task RNG(s) (``task_kwargs.random = seed``, docs/tasks.md §2; for
            Meta-World the ML1 task set and the task drawn at each reset, §4.6); None draws fresh
            entropy. ``reset(seed=...)`` reseeds later.
        reward_free: return reward 0.0 from ``step``; the task reward is still computed and put in
            ``info["task_reward"]`` (docs/tasks.md §3).
        render_mode: None or ``"rgb_array"``.

    Raises:
        dvfb.core.errors.ConfigError: unknown name (the message lists the valid names), or a task
            whose optional extra is not installed (the message says how to install it).
    """
    task_spec = resolve_task(name, reward_free=reward_free)
    check_domain(task_spec.domain)  # its optional extra may be missing
    module = domain_module(task_spec.domain)
    if hasattr(module, "make_gym_env"):  # a domain with its own front end (Meta-World)
        return module.make_gym_env(task_spec, seed, reward_free, render_mode)

    dmc_env = module.build_environment(task_spec.task, seed=seed)
    return DMCGymEnv(task_spec, dmc_env, reward_free=reward_free, render_mode=render_mode)
