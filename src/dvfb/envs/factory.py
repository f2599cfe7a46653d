"""``make``: build a task's gymnasium environment by name (docs/tasks.md §3, §5)."""

from __future__ import annotations

from dvfb.envs.gym_env import DMCGymEnv
from dvfb.envs.registry import domain_module, resolve_task


def make(
    name: str,
    seed: int | None = None,
    reward_free: bool = False,
    render_mode: str | None = None,
) -> DMCGymEnv:
    """Build the gymnasium environment of a task.

    Args:
        name: a full task name such as ``walker_flip`` (see ``dvfb.envs.TASKS``); with
            ``reward_free=True`` a bare domain name (``walker``) is also accepted and means the
            domain's pre-training task (docs/tasks.md §5).
        seed: seeds the task RNG(s) (``task_kwargs.random = seed``, docs/tasks.md §2); None draws fresh
            entropy. ``reset(seed=...)`` reseeds later.
        reward_free: return reward 0.0 from ``step``; the task reward is still computed and put in
            ``info["task_reward"]`` (docs/tasks.md §3).
        render_mode: None or ``"rgb_array"``.

    Raises:
        dvfb.errors.ConfigError: unknown name (the message lists the valid names).
    """
    task_spec = resolve_task(name, reward_free=reward_free)
    dmc_env = domain_module(task_spec.domain).build_environment(task_spec.task, seed=seed)
    return DMCGymEnv(task_spec, dmc_env, reward_free=reward_free, render_mode=render_mode)
