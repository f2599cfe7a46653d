"""Zero-shot and fine-tuning protocols: registered objects with typed configs (docs/methods.md, "Protocols").

A method's :class:`~dvfb.agents.registry.AgentSpec` names its family's protocols; everything above
the agents reaches them through :func:`zero_shot_protocol` and :func:`finetuner_class` (or
:func:`protocols_of` for a method), never by comparing family names.
"""

from __future__ import annotations

import dataclasses

from dvfb.agents import get_spec
from dvfb.core.config import flag_name
from dvfb.core.errors import ConfigError
from dvfb.protocols import dual_value, latent_search, urlb, zeroshot  # noqa: F401  (registration)
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


def protocols_of(agent: str, finetuner: str | None = None) -> tuple[type[ZeroShotProtocol], type[Finetuner]]:
    """The zero-shot protocol and the fine-tuner of a registered method (``finetuner``: one the
    method may choose instead of its own, :func:`finetuner_choices`; None: its own)."""
    spec = get_spec(agent)
    return zero_shot_protocol(spec.zero_shot), finetuner_class(resolve_finetuner(agent, finetuner))


def finetuner_choices(agent: str) -> tuple[str, ...]:
    """The fine-tuners a method may use: its own first, then those that declare they replace it."""
    own = get_spec(agent).finetuner
    return (own,) + tuple(name for name, cls in FINETUNERS.items() if own in cls.replaces)


def resolve_finetuner(agent: str, protocol: str | None = None) -> str:
    """The registered name of the fine-tuner a method fine-tunes with: ``protocol`` (``--protocol``),
    or the method's own when None; one line if the method cannot use it. What a fine-tuning run
    records and every later step reads is this name, never an empty one."""
    if protocol is None:
        return get_spec(agent).finetuner
    choices = finetuner_choices(agent)
    if protocol not in choices:
        raise ConfigError(f"--protocol {protocol} is not a protocol of {agent!r}; choose one of {', '.join(choices)}")
    return protocol


def finetuners_with_option(key: str) -> list[str]:
    """The registered fine-tuners whose config has the option ``key`` (a field name)."""
    return [name for name, cls in FINETUNERS.items() if key in {f.name for f in dataclasses.fields(cls.config_cls)}]


def check_finetune_options(finetuner: str, options: dict) -> None:
    """Refuse an option (``--finetune.*``) that the fine-tuner ``finetuner`` does not have, in one
    line naming it and the protocols that have it, before its config is built."""
    fields = {f.name for f in dataclasses.fields(finetuner_class(finetuner).config_cls)}
    for key in options:
        if key in fields:
            continue
        owners = finetuners_with_option(key)
        flag = flag_name(f"finetune.{key}")
        if not owners:
            raise ConfigError(f"{flag} is not an option of any fine-tuning protocol")
        raise ConfigError(f"{flag} is not an option of the {finetuner} protocol; it is an option of "
                          f"{', '.join(owners)} (--protocol)")


__all__ = ["FINETUNERS", "SKILL_SOURCES", "ZERO_SHOT_PROTOCOLS", "Finetuner", "FinetuneSchedule", "ZeroShotProtocol",
           "check_finetune_options", "finetuner_choices", "finetuner_class", "finetuners_with_option", "protocols_of",
           "resolve_finetuner", "zero_shot_protocol"]
