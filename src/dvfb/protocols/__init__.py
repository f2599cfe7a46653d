"""Zero-shot and fine-tuning protocols: registered objects with typed configs (docs/methods.md, "Protocols").

A method's :class:`~dvfb.agents.registry.AgentSpec` names its family's protocols; everything above
the agents reaches them through :func:`zero_shot_protocol` and :func:`finetuner_class` (or
:func:`protocols_of` for a method), never by comparing family names.
"""

from __future__ import annotations

from dvfb.agents import get_spec
from dvfb.errors import ConfigError
from dvfb.protocols import dual_value, latent_search, urlb, zero_shot  # noqa: F401  (registration)
from dvfb.protocols import online_inference  # noqa: F401  (registration)
from dvfb.protocols.base import (
    FINETUNERS,
    SKILL_SOURCES,
    ZERO_SHOT_PROTOCOLS,
    Finetuner,
    FinetuneSchedule,
    ZeroShotProtocol,
)


def zero_shot_protocol(name: str) -> type[ZeroShotProtocol]:
    try:
        return ZERO_SHOT_PROTOCOLS[name]
    except KeyError:
        raise ConfigError(f"unknown zero-shot protocol {name!r}; registered: {', '.join(ZERO_SHOT_PROTOCOLS)}") from None


def finetuner_class(name: str) -> type[Finetuner]:
    try:
        return FINETUNERS[name]
    except KeyError:
        raise ConfigError(f"unknown fine-tuner {name!r}; registered: {', '.join(FINETUNERS)}") from None


def protocols_of(agent: str, finetuner: str = "") -> tuple[type[ZeroShotProtocol], type[Finetuner]]:
    """The zero-shot protocol and the fine-tuner of a registered method (``finetuner``: one the
    method may choose instead of its own, :func:`finetuner_choices`; empty: its own)."""
    spec = get_spec(agent)
    return zero_shot_protocol(spec.zero_shot), finetuner_class(chosen_finetuner(agent, finetuner))


def finetuner_choices(agent: str) -> tuple[str, ...]:
    """The fine-tuners a method may use: its own first, then those that declare they replace it."""
    own = get_spec(agent).finetuner
    return (own,) + tuple(name for name, cls in FINETUNERS.items() if own in cls.replaces)


def chosen_finetuner(agent: str, protocol: str = "") -> str:
    """The fine-tuner's name for ``--protocol`` (empty: the method's own); one line if the method
    cannot use it."""
    if not protocol:
        return get_spec(agent).finetuner
    choices = finetuner_choices(agent)
    if protocol not in choices:
        raise ConfigError(f"--protocol {protocol} is not a protocol of {agent!r}; choose one of {', '.join(choices)}")
    return protocol


__all__ = ["FINETUNERS", "SKILL_SOURCES", "ZERO_SHOT_PROTOCOLS", "Finetuner", "FinetuneSchedule", "ZeroShotProtocol",
           "chosen_finetuner", "finetuner_choices", "finetuner_class", "protocols_of", "zero_shot_protocol"]
