"""The task registry: every task of docs/tasks.md §0 with its static facts, and name resolution.

This module imports neither dm_control, MuJoCo nor Meta-World, so listing tasks (``dvfb tasks``)
stays cheap. The domain modules that build the environments are imported lazily by
:func:`domain_module`. Domains that need an optional extra (Meta-World) are always listed; without
the extra, :func:`missing_extra` says so and how to install it.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
from types import ModuleType

from dvfb.core.errors import ConfigError


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
    module: str  # dvfb.envs.<module> builds the environment
    episode_length: int = 1000  # docs/tasks.md §2: 1000 steps for every DMC domain
    extra: str | None = None  # the optional extra (and package) the domain needs, if any


# docs/tasks.md §0 (dims, control dt, episode length), §2 and §5 (pre-training task).
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
    # docs/tasks.md §4.6: the authors' 250-step cap; pre-training on faucet-open (§5).
    "metaworld": _DomainFacts(
        ("faucet_open", "faucet_close"), 39, 4, 0.0125, "faucet_open", "meta_world",
        episode_length=250, extra="metaworld",
    ),
}

EXTRA_INSTALL = {"metaworld": "pip install -e '.[metaworld]'"}
"""How to install each optional extra (from a clone of the repository)."""

TASKS: dict[str, TaskSpec] = {
    f"{domain}_{task}": TaskSpec(
        name=f"{domain}_{task}",
        domain=domain,
        task=task,
        obs_dim=facts.obs_dim,
        action_dim=facts.action_dim,
        episode_length=facts.episode_length,
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


def _known_domain(domain: str) -> None:
    if domain not in DOMAINS:
        raise ConfigError(f"unknown domain {domain!r}; choose one of {', '.join(DOMAINS)}")


def check_domain(domain: str) -> None:
    """ConfigError with one line unless ``domain`` is known and can be built here (its optional
    extra, if any, installed): what a run checks before it creates anything."""
    _known_domain(domain)
    missing = missing_extra(domain)
    if missing:
        raise ConfigError(missing)


def tasks_of_domain(domain: str) -> list[str]:
    """Full names of the tasks of ``domain``, in registry order. Raises ConfigError if unknown."""
    _known_domain(domain)
    return [name for name, spec in TASKS.items() if spec.domain == domain]


def pretrain_task(domain: str) -> str:
    """The pre-training task of ``domain`` (docs/tasks.md §5). Raises ConfigError if unknown."""
    _known_domain(domain)
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


def missing_extra(name: str) -> str | None:
    """None if the task or domain ``name`` can be built here, else a line saying what to install."""
    domain = TASKS[name].domain if name in TASKS else name
    extra = _DOMAIN_FACTS[domain].extra
    if extra is None or importlib.util.find_spec(extra) is not None:
        return None
    return (f"the {domain} tasks need the optional extra {extra!r}, which is not installed: "
            f"{EXTRA_INSTALL[extra]}")


def domain_module(domain: str) -> ModuleType:
    """Import and return the module ``dvfb.envs.<domain>`` that builds the domain's tasks."""
    return importlib.import_module(f"dvfb.envs.{_DOMAIN_FACTS[domain].module}")


def format_task_table() -> str:
    """A markdown table of every task: name, domain, obs dim, action dim, episode length.

    Pre-training tasks (docs/tasks.md §5) are marked with ``*``; tasks whose optional extra is
    not installed are marked unavailable, with the install command below the table.
    """
    header = ("task", "domain", "obs dim", "action dim", "episode length")
    pretrain_names = set(DOMAINS.values())
    missing = {domain: missing_extra(domain) for domain in DOMAINS}
    rows = [
        (
            spec.name + (" *" if spec.name in pretrain_names else "")
            + (" (unavailable)" if missing[spec.domain] else ""),
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
    notes = [f"unavailable: {reason}" for reason in dict.fromkeys(filter(None, missing.values()))]
    return "\n".join([line(header), separator, *(line(row) for row in rows), "", footer, *notes])
