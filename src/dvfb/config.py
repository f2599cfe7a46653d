"""Typed configuration objects and their plumbing.

Every run is described by one dataclass instance. Fields are declared with :func:`param`, which
attaches a help text (shown by ``--help`` with the default) and optionally the allowed choices.
The helpers here serialise configs to JSON inside a run directory, read them back strictly
(unknown keys are an error, not silently dropped), and build ``argparse`` options from the fields.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from dvfb.errors import ConfigError

T = TypeVar("T")


def param(default: Any, help: str, choices: tuple | None = None) -> Any:
    """Declare a config field with a default, a help text and optional allowed values."""
    metadata = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def validate(config: Any) -> None:
    """Check every field with declared choices, recursing into nested configs."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            validate(value)
            continue
        choices = f.metadata.get("choices")
        if choices is not None and value not in choices:
            raise ConfigError(
                f"{type(config).__name__}.{f.name}={value!r} is not one of {list(choices)}"
            )


def to_dict(config: Any) -> dict:
    """A JSON-ready dict of a (possibly nested) config dataclass."""
    return dataclasses.asdict(config)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(name: str, tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(name, args[0], value)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{name}: expected a mapping, got {value!r}")
        return from_dict(tp, value)
    if origin in (list, tuple):
        (inner, *_rest) = typing.get_args(tp) or (Any,)
        seq = [_coerce(name, inner, v) for v in value]
        return tuple(seq) if origin is tuple else seq
    if tp is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if tp is int and isinstance(value, bool):
        raise ConfigError(f"{name}: expected an int, got {value!r}")
    if tp in (int, str, bool) and not isinstance(value, tp):
        raise ConfigError(f"{name}: expected {tp.__name__}, got {value!r}")
    return value


def from_dict(cls: type[T], data: dict) -> T:
    """Build ``cls`` from a dict, rejecting unknown keys and wrongly typed values."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} option(s): {', '.join(unknown)}")
    types_ = _field_types(cls)
    kwargs = {k: _coerce(f"{cls.__name__}.{k}", types_[k], v) for k, v in data.items()}
    config = cls(**kwargs)
    validate(config)
    return config


def save_json(config: Any, path: Path) -> None:
    path.write_text(json.dumps(to_dict(config), indent=2, sort_keys=True) + "\n")


def load_json(cls: type[T], path: Path) -> T:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read config {path}: {exc}") from exc
    return from_dict(cls, data)


def replace(config: T, **changes: Any) -> T:
    """``dataclasses.replace`` that validates the result and names unknown fields."""
    names = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(changes) - names)
    if unknown:
        raise ConfigError(f"unknown {type(config).__name__} option(s): {', '.join(unknown)}")
    new = dataclasses.replace(config, **changes)
    validate(new)
    return new


# ---------------------------------------------------------------------------------------------
# argparse bridge


def _parse_bool(text: str) -> bool:
    lowered = text.lower()
    if lowered in ("1", "true", "yes", "on"):
        return True
    if lowered in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean, got {text!r}")


def _optional(parser_fn):
    def parse(text: str):
        if text.lower() in ("none", "null"):
            return None
        return parser_fn(text)

    return parse


def add_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "",
                  defaults: Any | None = None, skip: tuple[str, ...] = ()) -> None:
    """Add one ``--option`` per field of ``cls`` (nested dataclasses get ``--outer.inner``).

    Options default to ``argparse.SUPPRESS`` so that only what the user typed overrides the preset;
    the help text shows the default of ``defaults`` (or of ``cls()``).
    """
    defaults = defaults if defaults is not None else cls()
    types_ = _field_types(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        tp = types_[f.name]
        default = getattr(defaults, f.name)
        flag = f"--{prefix}{f.name.replace('_', '-')}"
        if dataclasses.is_dataclass(tp):
            add_arguments(parser, tp, prefix=f"{prefix}{f.name}.", defaults=default)
            continue
        origin = typing.get_origin(tp)
        optional = origin in (typing.Union, types.UnionType)
        base = [a for a in typing.get_args(tp) if a is not type(None)][0] if optional else tp
        if typing.get_origin(base) in (list, tuple):
            inner = typing.get_args(base)[0]
            kwargs = dict(nargs="*", type=inner)
        elif base is bool:
            kwargs = dict(type=_parse_bool, metavar="BOOL")
        else:
            kwargs = dict(type=base)
        if optional and "type" in kwargs:
            kwargs["type"] = _optional(kwargs["type"])
        choices = f.metadata.get("choices")
        help_text = f.metadata.get("help", "")
        if choices:
            help_text += f" Choices: {', '.join(map(str, choices))}."
        parser.add_argument(flag, dest=f"{prefix}{f.name}", default=argparse.SUPPRESS,
                            help=f"{help_text} (default: {default!r})", **kwargs)


def overrides_from_args(args: argparse.Namespace, cls: type, prefix: str = "") -> dict:
    """The nested dict of the options the user actually passed for ``cls``."""
    out: dict = {}
    types_ = _field_types(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        tp = types_[f.name]
        if dataclasses.is_dataclass(tp):
            inner = overrides_from_args(args, tp, prefix=f"{key}.")
            if inner:
                out[f.name] = inner
        elif hasattr(args, key):
            out[f.name] = getattr(args, key)
    return out


def merge(config: T, overrides: dict) -> T:
    """Apply a nested override dict to a config, validating the result."""
    data = to_dict(config)

    def deep_update(base: dict, upd: dict) -> None:
        for k, v in upd.items():
            if isinstance(v, dict) and isinstance(base.get(k), dict):
                deep_update(base[k], v)
            else:
                base[k] = v

    deep_update(data, overrides)
    return from_dict(type(config), data)
