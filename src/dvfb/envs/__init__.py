"""The DVFB paper's tasks behind a gymnasium API: DeepMind Control (docs/tasks.md §0-§6) and,
with the optional extra, Meta-World's faucet tasks (§4.6, §7).

Public API::

    make(name, seed=None, reward_free=False) -> gymnasium.Env
    TASKS: dict[str, TaskSpec]      # every task, by full name "<domain>_<task>"
    DOMAINS: dict[str, str]         # domain -> its reward-free pre-training task (docs/tasks.md §5)
    tasks_of_domain(domain), pretrain_task(domain), format_task_table()

Importing this package also registers every task with gymnasium as ``dvfb/<name>``, so
``gymnasium.make("dvfb/walker_flip", seed=0)`` works. The registration adds no TimeLimit wrapper:
the environment truncates itself at its episode length (docs/tasks.md §2, §4.6). The Meta-World
names are registered even without the extra; making one then says how to install it.
"""

from dvfb.envs._mujoco_gl import configure_default_mujoco_gl

# Must run before anything imports dm_control (see _mujoco_gl for the policy).
configure_default_mujoco_gl()

import gymnasium as _gymnasium  # noqa: E402

from dvfb.envs.factory import make  # noqa: E402
from dvfb.envs.gym_env import DMCGymEnv  # noqa: E402
from dvfb.envs.registry import (  # noqa: E402
    DOMAINS,
    TASKS,
    TaskSpec,
    check_domain,
    format_task_table,
    missing_extra,
    pretrain_task,
    resolve_task,
    tasks_of_domain,
)

GYMNASIUM_NAMESPACE = "dvfb"

__all__ = [
    "DMCGymEnv",
    "DOMAINS",
    "GYMNASIUM_NAMESPACE",
    "TASKS",
    "TaskSpec",
    "check_domain",
    "format_task_table",
    "make",
    "missing_extra",
    "pretrain_task",
    "resolve_task",
    "tasks_of_domain",
]


def _register_with_gymnasium() -> None:
    """Register ``dvfb/<name>`` for every task; keyword arguments of ``make`` pass through."""
    for task_name in TASKS:
        env_id = f"{GYMNASIUM_NAMESPACE}/{task_name}"
        if env_id in _gymnasium.registry:
            continue
        _gymnasium.register(
            id=env_id,
            entry_point="dvfb.envs.factory:make",
            kwargs={"name": task_name},
            max_episode_steps=None,  # the env truncates itself; no TimeLimit wrapper
        )


_register_with_gymnasium()
