"""The registry of methods: each agent module registers one :class:`AgentSpec` beside its class.

Everything above the agents asks the registry, never a hard-coded list: the ``--agent`` choices and
the agent's config flags of the CLI, the run config's sections (typed, strict), the presets, the
names of the zero-shot and fine-tuning protocols of the method's family, and the method labels of
the reports.
Adding a method is its own module ending in :func:`register`, plus one import line in
:mod:`dvfb.agents` (docs/adding_a_method.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from dvfb.core.errors import ConfigError
from dvfb.envs import pretrain_task


@dataclass(frozen=True)
class AgentSpec:
    """What the rest of the package needs to know about a method.

    ``sections`` are the agent's typed config sections, each a dataclass that becomes a section
    of the run config (``--SECTION.FIELD`` flags). ``zero_shot`` and ``finetuner`` name the
    registered protocols of the method's family (docs/methods.md, "Protocols"): their config
    classes become the run config's ``inference`` and ``finetune`` sections. ``presets`` maps a
    preset name to overrides of the run config (missing presets mean the spec's values);
    ``defaults`` overrides the run config's fields for this method. ``label(run_config,
    finetune_config)`` names the method in reports (variants such as ``dvfb_wo_ce``); by default
    the agent's name. ``column`` orders the report's columns; ``task_field`` names the config field
    holding the task of a method that learns from its reward (the supervised reference). ``coefficients``
    lists ``(dotted field, short name)`` pairs of the method's coefficients whose value, where it differs
    from the run's preset, names a variant in the reports (``dvfb_alpha3``: the paper's ablations;
    :func:`dvfb.analysis.common.method_name`). ``moved_fields`` maps a top-level
    field of configs written by older versions to where it lives now (``"update_z_every":
    "fb.skill_every"``; None: dropped), so that old run directories still load.
    """

    name: str
    agent_cls: type
    summary: str
    family: str
    sections: dict[str, type]
    zero_shot: str
    finetuner: str
    presets: dict[str, dict] = field(default_factory=dict)
    defaults: dict[str, Any] = field(default_factory=dict)
    label: Callable[[Any, Any], str] | None = None
    column: int = 100  # position of the method's columns in report tables (ties: registry order)
    moved_fields: dict[str, str | None] = field(default_factory=dict)
    coefficients: tuple[tuple[str, str], ...] = ()
    # A method that learns from a task's reward (the supervised reference): the dotted run-config
    # field that names the task. None for the reward-free methods. Such a run trains in the
    # task's environment and is evaluated on that task only; a sweep gives it a cell per task.
    task_field: str | None = None

    def task_of(self, run_config: Any) -> str | None:
        """The task a run of this method learns from, or None (reward-free pre-training)."""
        if self.task_field is None:
            return None
        value = run_config
        for part in self.task_field.split("."):
            value = config_field(value, part)
        if not value:  # empty: the domain's pre-training task
            return pretrain_task(config_field(run_config, "domain"))
        return value

    def method_label(self, run_config: Any, finetune_config: Any = None) -> str:
        """The report's name for a run (configs as dataclasses or dicts)."""
        return self.label(run_config, finetune_config) if self.label is not None else self.name


AGENTS: dict[str, AgentSpec] = {}


def register(spec: AgentSpec) -> AgentSpec:
    """Add a method to the registry (called once, at the end of its module)."""
    if spec.name in AGENTS and AGENTS[spec.name].agent_cls is not spec.agent_cls:
        raise ValueError(f"agent {spec.name!r} is registered twice")
    AGENTS[spec.name] = spec
    return spec


def agent_names() -> tuple[str, ...]:
    return tuple(AGENTS)


def get_spec(name: str) -> AgentSpec:
    """The spec of a registered method; an unknown name is a :class:`ConfigError` listing the choices."""
    try:
        return AGENTS[name]
    except KeyError:
        raise ConfigError(f"unknown agent {name!r}; choose one of {', '.join(AGENTS)}") from None


def config_field(config: Any, name: str, default: Any = None) -> Any:
    """``config.name`` or ``config[name]``: labels read configs as dataclasses or JSON dicts."""
    if isinstance(config, dict):
        return config.get(name, default)
    return getattr(config, name, default)
