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
import math
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from dvfb.core.errors import ConfigError

T = TypeVar("T")

# The seeds numpy's and torch's generators accept: 0 .. 2**32 - 1 (numpy's legacy seeding, which
# environments use, refuses larger ones).
SEED_MAX = 2**32 - 1
# Every integer field fits a 64-bit integer, so that no value overflows inside torch or numpy.
INT_RANGE = (-(2**63), 2**63 - 1)


def param(default: Any, help: str, choices: tuple | None = None, *, at_least: float | None = None,
          above: float | None = None, at_most: float | None = None) -> Any:
    """Declare a config field with a default, a help text, and optionally its allowed values:
    ``choices``, or a range (``at_least`` / ``above`` a lower bound, ``at_most`` an upper one).

    Float fields must also be finite (no NaN or inf) unless their default is not: validation checks
    all of it when a config is built from a dict, replaced or merged (:func:`validate`).
    """
    metadata: dict[str, Any] = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    bounds = {k: v for k, v in (("at_least", at_least), ("above", above), ("at_most", at_most)) if v is not None}
    if bounds:
        metadata["bounds"] = bounds
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def seed_param(default: int, help: str) -> Any:
    """A seed field: an integer in 0 .. :data:`SEED_MAX`."""
    return param(default, help, at_least=0, at_most=SEED_MAX)


def flag_name(path: str) -> str:
    """The command-line flag of a config field path: sections keep their underscores, the field name
    gets dashes (``fb.batch_size`` -> ``--fb.batch-size``, ``icm_apt.rep_dim`` -> ``--icm_apt.rep-dim``)."""
    *sections, name = path.split(".")
    return "--" + ".".join([*sections, name.replace("_", "-")])


def _number(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def _range_text(bounds: dict) -> str:
    parts = []
    if "at_least" in bounds:
        parts.append(f">= {_number(bounds['at_least'])}")
    if "above" in bounds:
        parts.append(f"> {_number(bounds['above'])}")
    if "at_most" in bounds:
        parts.append(f"<= {_number(bounds['at_most'])}")
    return " and ".join(parts)


def _check_value(path: str, value: Any, metadata: Any) -> None:
    choices = metadata.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{flag_name(path)} {value!r} is not one of {', '.join(map(str, choices))}")
    values = value if isinstance(value, (list, tuple)) else [value]
    for item in values:
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            continue
        if isinstance(item, float) and not math.isfinite(item):
            raise ConfigError(f"{flag_name(path)} {item!r} is not a finite number")
        if isinstance(item, int) and not INT_RANGE[0] <= item <= INT_RANGE[1]:
            raise ConfigError(f"{flag_name(path)} {item} is out of range: it must fit a 64-bit integer")
        bounds = metadata.get("bounds")
        if bounds and (("at_least" in bounds and item < bounds["at_least"])
                       or ("above" in bounds and item <= bounds["above"])
                       or ("at_most" in bounds and item > bounds["at_most"])):
            raise ConfigError(f"{flag_name(path)} {item!r} is out of range: it must be {_range_text(bounds)}")


def require_updates(frames_flag: str, frames: int, seed_flag: str, seed_frames: int) -> None:
    """A training loop's relation: more frames than seed frames, or no update would run."""
    if frames <= seed_frames:
        raise ConfigError(f"{frames_flag} {frames} must be larger than {seed_flag} {seed_frames}: no update would run")


def validate(config: Any, path: str = "") -> None:
    """Check every field's choices, range and finiteness, recursing into nested configs, then the
    relations a config class declares in a ``check()`` method. Errors name the flag and the value."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        field_path = f"{path}{f.name}"
        if dataclasses.is_dataclass(value):
            validate(value, f"{field_path}.")
            continue
        _check_value(field_path, value, f.metadata)
    check = getattr(config, "check", None)
    if callable(check):
        check()


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
        return from_dict(tp, value, check=False)  # validated as a whole by the outermost call
    if origin in (list, tuple):
        # A string or a number is not a list: "dvfb" must not become ["d", "v", "f", "b"].
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        (inner, *_rest) = typing.get_args(tp) or (Any,)
        seq = [_coerce(name, inner, v) for v in value]
        return tuple(seq) if origin is tuple else seq
    if origin is dict and not isinstance(value, dict):
        raise ConfigError(f"{name}: expected a mapping, got {value!r}")
    if value is None and tp is not Any:
        raise ConfigError(f"{name}: expected {getattr(tp, '__name__', tp)}, got None")
    if tp is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if tp is int and isinstance(value, bool):
        raise ConfigError(f"{name}: expected an int, got {value!r}")
    # A float from text ("fast", or "1e-4" from a sweep file) would pass every range check and fail
    # only when the run starts: refused here as the other scalar types are.
    if tp in (int, float, str, bool) and not isinstance(value, tp):
        raise ConfigError(f"{name}: expected {tp.__name__}, got {value!r}")
    return value


def from_dict(cls: type[T], data: dict, check: bool = True, prefix: str = "",
              section_types: dict[str, type] | None = None) -> T:
    """Build ``cls`` from a dict, rejecting unknown keys and wrongly typed values; with ``check``
    (the outermost call), also :func:`validate` the result, naming nested fields by their path
    (``prefix`` is the path of ``cls`` itself, e.g. ``"inference."``). ``section_types``: the
    classes of sections that ``cls`` declares by a base class or ``Any`` (a fine-tuning run's
    ``finetune`` section is its fine-tuner's config, a subclass of the schedule it declares)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{cls.__name__}: expected a mapping of options, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} option(s): {', '.join(unknown)}")
    types_ = {**_field_types(cls), **(section_types or {})}
    kwargs = {k: _coerce(f"{cls.__name__}.{k}", types_[k], v) for k, v in data.items()}
    config = cls(**kwargs)
    if check:
        validate(config, prefix)
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


def canonical_key(key: str) -> str:
    """``fb.hidden-dim`` -> ``fb.hidden_dim`` (config field names never contain dashes)."""
    return key.strip().lstrip("-").replace("-", "_")


def field_type(cls: type, key: str) -> Any | None:
    """The declared type of the dotted field ``key`` of the config class ``cls``; None if absent."""
    tp: Any = cls
    for part in key.split("."):
        if not (isinstance(tp, type) and dataclasses.is_dataclass(tp)):
            return None
        hints = typing.get_type_hints(tp)
        if part not in hints or part not in {f.name for f in dataclasses.fields(tp)}:
            return None
        tp = hints[part]
    return tp


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [a for a in typing.get_args(tp) if a is not type(None)][0], True
    return tp, False


def is_list_type(tp: Any) -> bool:
    return typing.get_origin(_strip_optional(tp)[0]) in (list, tuple)


def parse_text(key: str, tp: Any, text: str) -> Any:
    """A command-line value of the dotted field ``key`` as its declared type ``tp``, as the flags of
    :func:`add_arguments` parse it (a list: comma-separated values)."""
    base, optional = _strip_optional(tp)
    text = text.strip()
    if optional and text.lower() in ("none", "null"):
        return None
    if typing.get_origin(base) in (list, tuple):
        inner = typing.get_args(base)[0]
        return [parse_text(key, inner, item) for item in text.split(",") if item.strip()]
    try:
        if base is bool:
            return _parse_bool(text)
        if base in (int, float, str):
            return base(text)
    except (ValueError, argparse.ArgumentTypeError):
        raise ConfigError(f"{flag_name(key)}: {text!r} is not a valid {getattr(base, '__name__', base)}") from None
    return text


def format_value(value: Any) -> str:
    """The command-line text of a typed value; :func:`parse_text` reads it back exactly."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return ",".join(format_value(v) for v in value)
    return repr(value) if isinstance(value, float) else str(value)



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
                  defaults: Any | None = None, skip: tuple[str, ...] = (), *,
                  default_text: Callable[[str], Any] | None = None, deprecated_prefix: str | None = None,
                  alias_action: type | None = None) -> None:
    """Add one ``--option`` per field of ``cls`` (nested dataclasses get ``--outer.inner``).

    Options default to ``argparse.SUPPRESS`` so that only what the user typed overrides the preset;
    the help text shows the default of ``defaults`` (or of ``cls()``), or ``default_text(name)`` for
    the field ``name`` (dotted below ``cls``), an object whose ``str()`` is taken only when the help
    is shown. ``deprecated_prefix``: an older prefix whose flags still set the same options, left out
    of the help, through ``alias_action`` (an argparse Action that takes ``deprecated``, the old
    option strings, and ``replacement``, the flag to use instead).
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
            inner_text = None if default_text is None else (lambda name, outer=f.name: default_text(f"{outer}.{name}"))
            add_arguments(parser, tp, prefix=f"{prefix}{f.name}.", defaults=default, default_text=inner_text,
                          deprecated_prefix=None if deprecated_prefix is None else f"{deprecated_prefix}{f.name}.",
                          alias_action=alias_action)
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
        # argparse fills %(default_text)s from the action when it formats the help, so a text that
        # costs work (building every preset's config) is made only for --help.
        shown = "%(default_text)s" if default_text is not None else repr(default).replace("%", "%%")
        action = parser.add_argument(flag, dest=f"{prefix}{f.name}", default=argparse.SUPPRESS,
                                     help=f"{help_text} (default: {shown})", **kwargs)
        if default_text is not None:
            action.default_text = default_text(f.name)
        if deprecated_prefix is not None:
            old = f"--{deprecated_prefix}{f.name.replace('_', '-')}"
            parser.add_argument(old, dest=f"{prefix}{f.name}", default=argparse.SUPPRESS, help=argparse.SUPPRESS,
                                action=alias_action, deprecated=(old,), replacement=flag, **kwargs)


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


def merge(config: T, overrides: dict, prefix: str = "") -> T:
    """Apply a nested override dict to a config, validating the result (errors name the fields
    with ``prefix``, the path of ``config`` in its run config)."""
    data = to_dict(config)

    def deep_update(base: dict, upd: dict) -> None:
        for k, v in upd.items():
            if isinstance(v, dict) and isinstance(base.get(k), dict):
                deep_update(base[k], v)
            else:
                base[k] = v

    deep_update(data, overrides)
    return from_dict(type(config), data, prefix=prefix)
