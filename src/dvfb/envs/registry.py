"""The task registry: every DMC task of docs/tasks.md §0 with its static facts, and name resolution.

This module imports neither dm_control nor MuJoCo, so listing tasks (``dvfb tasks``) stays cheap.
The domain modules that build the environments are imported lazily by :func:`domain_module`.
"""

from __future__ import annotations

import dataclasses
import importlib
from types import ModuleType

from dvfb.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Static description of one task (docs/tasks.md §0 summary table).

    Attributes:
        name: full task name, ``<domain>_<task>``, e.g. ``hopper_hop_backward``.
        domain: domain name, e.g. ``hopper`` or ``point_mass_maze``.
        task: task name within the domain, e.g. ``hop_backward``.
        obs_dim: length of the flat float32 observation.
        action_dim: number of actuators (length of the action in [-1, 1]).
        episode_length: env steps per episode; the episode is truncated (never terminated) there.
        control_dt: seconds of simulated time per env step.
    """

    name: str
    domain: str
    task: str
    obs_dim: int
    action_dim: int
    episode_length: int
    control_dt: float


@dataclasses.dataclass(frozen=True)
class _DomainFacts:
    tasks: tuple[str, ...]
    obs_dim: int
    action_dim: int
    control_dt: float
    pretrain_task: str  # the authors' pre-training ("primal") task, docs/tasks.md §5
    module: str  # dvfb.envs.<module> builds the dm_control environment


# docs/tasks.md §0 (dims, control dt), §2 (1000 steps for every DMC domain) and §5 (pre-training task).
_EPISODE_LENGTH = 1000
_DOMAIN_FACTS: dict[str, _DomainFacts] = {
    "walker": _DomainFacts(("stand", "walk", "run", "flip"), 24, 6, 0.025, "walk", "walker"),
    "quadruped": _DomainFacts(("stand", "walk", "jump", "run"), 78, 12, 0.02, "walk", "quadruped"),
    "hopper": _DomainFacts(
        ("hop", "flip", "hop_backward", "flip_backward"), 15, 4, 0.02, "hop", "hopper"
    ),
    "cheetah": _DomainFacts(
        ("run", "run_backward", "walk", "walk_backward"), 17, 6, 0.01, "walk", "cheetah"
    ),
    "point_mass_maze": _DomainFacts(
        ("reach_top_left", "reach_top_right", "reach_bottom_left", "reach_bottom_right"),
        4,
        2,
        0.02,
        "reach_top_left",
        "point_mass_maze",
    ),
}

TASKS: dict[str, TaskSpec] = {
    f"{domain}_{task}": TaskSpec(
        name=f"{domain}_{task}",
        domain=domain,
        task=task,
        obs_dim=facts.obs_dim,
        action_dim=facts.action_dim,
        episode_length=_EPISODE_LENGTH,
        control_dt=facts.control_dt,
    )
    for domain, facts in _DOMAIN_FACTS.items()
    for task in facts.tasks
}
"""Every task, by full name, in domain order (docs/tasks.md §0)."""

DOMAINS: dict[str, str] = {
    domain: f"{domain}_{facts.pretrain_task}" for domain, facts in _DOMAIN_FACTS.items()
}
"""Domain -> the full name of its reward-free pre-training task (docs/tasks.md §5, authors' column)."""


def tasks_of_domain(domain: str) -> list[str]:
    """Full names of the tasks of ``domain``, in registry order. Raises ConfigError if unknown."""
    if domain not in DOMAINS:
        raise ConfigError(f"unknown domain {domain!r}; valid domains: {', '.join(DOMAINS)}")
    return [name for name, spec in TASKS.items() if spec.domain == domain]


def pretrain_task(domain: str) -> str:
    """The pre-training task of ``domain`` (docs/tasks.md §5). Raises ConfigError if unknown."""
    if domain not in DOMAINS:
        raise ConfigError(f"unknown domain {domain!r}; valid domains: {', '.join(DOMAINS)}")
    return DOMAINS[domain]


def resolve_task(name: str, reward_free: bool = False) -> TaskSpec:
    """Map a user-given name to its TaskSpec.

    A full task name always resolves to itself. A bare domain name resolves to the domain's
    pre-training task (docs/tasks.md §5), but only in reward-free mode: a downstream (reward-using) run
    must say which task it means. Anything else raises :class:`ConfigError` listing valid names.
    """
    if name in TASKS:
        return TASKS[name]
    if name in DOMAINS:
        if reward_free:
            return TASKS[DOMAINS[name]]
        raise ConfigError(
            f"{name!r} is a domain, not a task; a bare domain is only accepted with "
            f"reward_free=True (it then means {DOMAINS[name]!r}). "
            f"Tasks of {name!r}: {', '.join(tasks_of_domain(name))}"
        )
    raise ConfigError(
        f"unknown task {name!r}. Valid tasks: {', '.join(TASKS)}. "
        f"Valid domains (reward-free pre-training only): {', '.join(DOMAINS)}"
    )


def domain_module(domain: str) -> ModuleType:
    """Import and return the module ``dvfb.envs.<domain>`` that builds the domain's tasks."""
    return importlib.import_module(f"dvfb.envs.{_DOMAIN_FACTS[domain].module}")


def format_task_table() -> str:
    """A markdown table of every task: name, domain, obs dim, action dim, episode length.

    Pre-training tasks (docs/tasks.md §5) are marked with ``*``.
    """
    header = ("task", "domain", "obs dim", "action dim", "episode length")
    pretrain_names = set(DOMAINS.values())
    rows = [
        (
            spec.name + (" *" if spec.name in pretrain_names else ""),
            spec.domain,
            str(spec.obs_dim),
            str(spec.action_dim),
            str(spec.episode_length),
        )
        for spec in TASKS.values()
    ]
    widths = [max(len(row[i]) for row in (header, *rows)) for i in range(len(header))]

    def line(cells: tuple[str, ...]) -> str:
        return (
            "| " + " | ".join(cell.ljust(w) for cell, w in zip(cells, widths, strict=True)) + " |"
        )

    separator = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    footer = "* = reward-free pre-training task of its domain (used when only the domain is given)"
    return "\n".join([line(header), separator, *(line(row) for row in rows), "", footer])
