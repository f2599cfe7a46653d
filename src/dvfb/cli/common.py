"""What the commands share: the help formatter, run-directory and goal parsing, the pre-training
config from flags, and the ``--inference.*`` / ``--finetune.*`` flags of the registered protocols."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dvfb.agents import agent_names, get_spec
from dvfb.core.config import (INT_RANGE, SEED_MAX, add_arguments, canonical_key, field_type, flag_name, merge,
                              overrides_from_args)
from dvfb.core.errors import ConfigError
from dvfb.protocols import FINETUNERS, ZERO_SHOT_PROTOCOLS, FinetuneSchedule
from dvfb.runs.export import is_export
from dvfb.runs.presets import preset_config
from dvfb.runs.run_config import GENERIC_PRESETS, run_config_class
from dvfb.workflows.resources import run_or_export

DEFAULT_PRESET = "small"


class Formatter(argparse.RawDescriptionHelpFormatter):
    pass


class Parser(argparse.ArgumentParser):
    """The parser of ``dvfb`` and of each command: a bad flag or value is one line naming it, exit
    status 2, as every other bad input is (argparse prints its whole usage first, which for
    ``dvfb pretrain`` is dozens of lines burying the one that matters)."""

    def error(self, message: str):
        hint = "" if "--help" in message else f" (`{self.prog} --help` lists the options)"
        self.exit(2, f"{self.prog}: error: {message}{hint}\n")


def unknown_option_message(args: argparse.Namespace, extra: list[str]) -> str:
    """What to say of command-line words no option of the command took: for ``dvfb pretrain``, a
    config option of another method names the methods that have it (the flags depend on --agent)."""
    if getattr(args, "command", None) == "pretrain":
        for word in extra:
            if not word.startswith("--"):
                continue
            key = canonical_key(word.split("=", 1)[0])
            owners = [name for name in agent_names() if field_type(run_config_class(name), key) is not None]
            if owners:
                return (f"{word.split('=', 1)[0]} is an option of {', '.join(owners)}, not of --agent {args.agent}; "
                        f"`dvfb pretrain --agent {args.agent} --help` lists its options")
    return f"unrecognized arguments: {' '.join(extra)}"


def default_run_dir(config) -> Path:
    return Path("runs") / f"{config.agent}_{config.domain}_{config.preset}_s{config.seed}"


def parse_goal(text: str) -> np.ndarray:
    path = Path(text)
    if path.suffix == ".npy":
        if not path.exists():
            raise ConfigError(f"goal file {path} does not exist")
        return np.load(path)
    try:
        return np.array([float(x) for x in text.split(",")], dtype=np.float32)
    except ValueError as exc:
        raise ConfigError(f"--goal must be a .npy file or comma-separated numbers, got {text!r}") from exc


def pretrain_config(args: argparse.Namespace):
    base = preset_config(args.preset, args.agent)
    return merge(base, overrides_from_args(args, run_config_class(args.agent)))


def protocol_classes(kind: str, online: bool = False) -> list[type]:
    """The config classes of every registered zero-shot protocol (``inference``) or fine-tuner
    (``online``: only the fine-tuners that infer the task online, ``dvfb zeroshot --protocol``)."""
    registry = ZERO_SHOT_PROTOCOLS if kind == "inference" else FINETUNERS
    classes: list[type] = []
    for protocol in registry.values():
        if online and getattr(protocol, "infers_skill", True):
            continue
        if protocol.config_cls not in classes:
            classes.append(protocol.config_cls)
    return classes


class PresetDefault:
    """The default of an ``--inference.*`` / ``--finetune.*`` option in ``--help``: the value in the
    run's config, which its preset chose (README.md, "Using it"), by preset. ``str()`` builds every
    method's preset configs, so it runs only when the help is shown."""

    def __init__(self, kind: str, name: str, fallback: Any):
        self.kind, self.name, self.fallback = kind, name, fallback

    def __str__(self) -> str:
        groups: dict[str, list[str]] = {}
        for preset in GENERIC_PRESETS:
            values = set()
            for agent in agent_names():
                section = getattr(preset_config(preset, agent), self.kind, None)
                if section is not None and hasattr(section, self.name):
                    values.add(repr(getattr(section, self.name)))
            if not values:  # no run config carries it: the protocol's own default
                return repr(self.fallback)
            groups.setdefault(values.pop() if len(values) == 1 else "by method", []).append(preset)
        if len(groups) == 1:
            return f"the run's, {next(iter(groups))} at every preset"
        return "the run's, by its preset: " + "; ".join(f"{' and '.join(presets)} {value}"
                                                        for value, presets in groups.items())


def add_protocol_arguments(p: argparse.ArgumentParser, kind: str, online: bool = False, prefix: str | None = None,
                           deprecated_prefix: str | None = None) -> None:
    """``--inference.*`` flags, or ``dvfb zeroshot``'s options of the fine-tuners that infer the
    task online (``kind`` "finetune", ``online``): the union of the protocols' fields, each once,
    named ``--<prefix>.*`` when ``prefix`` is given (``deprecated_prefix``: an older name that still
    works, saying so on stderr). ``dvfb finetune``'s options are :func:`add_finetune_arguments`.

    Which of them apply depends on the run's method; a flag its family lacks is an error naming
    the family's config class when the run is loaded. The defaults shown are those a run's preset
    gave its config; the options of a protocol that starts from its own config (``online``) show
    that config's.
    """
    prefix = prefix or kind
    seen: set[str] = set()
    for cls in protocol_classes(kind, online):
        _option_group(p, f"{prefix} options ({cls.__name__})", None, cls, seen, kind, online, prefix,
                      deprecated_prefix)


def add_finetune_arguments(p: argparse.ArgumentParser) -> None:
    """``dvfb finetune``'s ``--finetune.*`` flags, one group per registered fine-tuner under its
    name after the schedule every fine-tuner shares; an option two fine-tuners share is listed in
    the first one's group and named in the other's description. The run's fine-tuner takes only its
    own options (:func:`dvfb.protocols.check_finetune_options` refuses the others)."""
    seen: set[str] = set()
    _option_group(p, "finetune options of every protocol (FinetuneSchedule)", None, FinetuneSchedule, seen,
                  "finetune")
    holder: dict[str, str] = {}  # option -> the fine-tuner whose group lists it
    for name, cls in FINETUNERS.items():
        owners = [agent for agent in agent_names() if get_spec(agent).finetuner == name]
        used = (f"the fine-tuner of {', '.join(owners)}" if owners else
                f"chosen with --protocol {name} instead of {', '.join(cls.replaces)}")
        shared = [f"{flag_name(f'finetune.{f.name}')} (listed under {holder[f.name]})"
                  for f in dataclasses.fields(cls.config_cls) if f.name in holder]
        description = textwrap.fill(used + (f"; also {', '.join(shared)}" if shared else ""), 100)
        new = [f.name for f in dataclasses.fields(cls.config_cls) if f.name not in seen]
        holder.update((key, name) for key in new)
        _option_group(p, f"--protocol {name} ({cls.config_cls.__name__})", description, cls.config_cls, seen,
                      "finetune")


def _option_group(p: argparse.ArgumentParser, title: str, description: str | None, cls: type, seen: set[str],
                  kind: str, online: bool = False, prefix: str | None = None,
                  deprecated_prefix: str | None = None) -> None:
    """One help group of the fields of ``cls`` that no earlier group has (``seen``, updated)."""
    prefix = prefix or kind
    skip = tuple(f.name for f in dataclasses.fields(cls) if f.name in seen)
    if len(skip) < len(dataclasses.fields(cls)):
        group = p.add_argument_group(title, description)
        defaults = cls()
        text = None if online else (lambda name, d=defaults: PresetDefault(kind, name, _dotted(d, name)))
        add_arguments(group, cls, prefix=f"{prefix}.", skip=skip, default_text=text,
                      deprecated_prefix=f"{deprecated_prefix}." if deprecated_prefix else None,
                      alias_action=DeprecatedAlias)
    seen.update(f.name for f in dataclasses.fields(cls))


def _dotted(config: Any, name: str) -> Any:
    for part in name.split("."):
        config = getattr(config, part)
    return config


def protocol_overrides(args: argparse.Namespace, kind: str, online: bool = False, prefix: str | None = None) -> dict:
    """The ``--<prefix>.*`` options given (``prefix``: ``kind`` unless named otherwise)."""
    out: dict = {}
    for cls in protocol_classes(kind, online):
        out.update(overrides_from_args(args, cls, prefix=f"{prefix or kind}."))
    return out


def add_snapshot_and_seed(p: argparse.ArgumentParser, seed_what: str = "seed") -> None:
    """--snapshot and --seed of the commands that load a pre-trained run's agent."""
    p.add_argument("--snapshot", type=integer(0), default=None, help="snapshot frames (default: the latest)")
    p.add_argument("--seed", type=seed_value, default=None, help=f"{seed_what} (default: the run's seed)")


def seed_value(text: str) -> int:
    """A seed: an integer in 0 .. 2**32 - 1, what numpy and torch accept (argparse names the flag
    when this raises)."""
    value = int(text)
    if not 0 <= value <= SEED_MAX:
        raise ValueError(text)
    return value


seed_value.__name__ = f"seed (an integer from 0 to {SEED_MAX})"  # how argparse names the type in its error


def integer(minimum: int = 1, maximum: int = INT_RANGE[1]) -> Callable[[str], int]:
    """An argparse type: an integer in ``minimum .. maximum``; argparse's one-line error names the
    flag, the value and the range."""
    def parse(text: str) -> int:
        value = int(text)
        if not minimum <= value <= maximum:
            raise ValueError(text)
        return value

    parse.__name__ = (f"integer >= {minimum}" if maximum == INT_RANGE[1]
                      else f"integer from {minimum} to {maximum}")
    return parse


def seed_list(text: str) -> list[int]:
    """Seeds ``0,1,2`` (each an integer >= 0) of a group (docs/members.md)."""
    seeds = [seed_value(part) for part in text.split(",")]
    if not seeds:
        raise ValueError(text)
    return seeds


seed_list.__name__ = f"seeds (comma-separated integers from 0 to {SEED_MAX})"

SEED_PLACEHOLDER = "{seed}"


def member_run_dirs(config, run_dir: str | None, seeds: list[int]) -> list[Path]:
    """The run directory of each member of a group: ``--run-dir`` with ``{seed}`` replaced by the
    member's seed, or each seed's default run directory."""
    if run_dir is None:
        return [default_run_dir(dataclasses.replace(config, seed=seed)) for seed in seeds]
    if SEED_PLACEHOLDER not in run_dir:
        raise ConfigError(f"--run-dir {run_dir} with --seeds needs {SEED_PLACEHOLDER} in it (one run directory "
                          f"per member, e.g. runs/fb_walker_s{SEED_PLACEHOLDER})")
    return [Path(run_dir.replace(SEED_PLACEHOLDER, str(seed))) for seed in seeds]


def eval_dir_flag(p: argparse.ArgumentParser) -> None:
    """``--eval-dir`` of the commands that evaluate an exported model (docs/sharing.md, "Evaluate")."""
    p.add_argument("--eval-dir", default=None,
                   help="for an exported model: the run directory it is evaluated in, made from it the first time "
                        "and reused after; results go there, the export's own files are never written (default: "
                        "EXPORT.eval beside the exported model)")


@contextlib.contextmanager
def evaluated(paths: str | list[str], eval_dir: str | None, command: list[str] | None):
    """What a command evaluates, as ``(run directories, inference data, exported)``: ``paths`` as
    they are, or one exported model's evaluation directory with its inference samples
    (:func:`~dvfb.workflows.resources.run_or_export`)."""
    paths = [paths] if isinstance(paths, str) else list(paths)
    if len(paths) == 1:
        with run_or_export(paths[0], eval_dir, command) as (run, data):
            yield [str(run)], data, is_export(paths[0])
        return
    exported = next((path for path in paths if is_export(path)), None)
    if exported is not None:
        raise ConfigError(f"{exported} is an exported model: evaluate exported models one at a time")
    if eval_dir is not None:
        raise ConfigError("--eval-dir is where an exported model is evaluated; these are run directories")
    yield paths, None, False


def torch_threads_flag(p: argparse.ArgumentParser, on_run: bool = True) -> None:
    """``--torch-threads`` of a command that computes, the same flag as pre-training's (README.md,
    "Threads and progress"); ``on_run``: the command uses a pre-training run, whose own setting is
    its default."""
    default = ("the run's own --torch-threads when it set one, at most the CPUs this process may use; else as 0"
               if on_run else "0")
    p.add_argument("--torch-threads", dest="torch_threads", type=integer(0), default=None if on_run else 0,
                   help="torch threads of this command; 0: OMP_NUM_THREADS when set, else half the CPUs this "
                        f"process may use (its affinity and cgroup quota), at least one (default: {default})")


def progress_flag(p: argparse.ArgumentParser) -> None:
    """--progress / --no-progress of the commands with a progress bar."""
    p.add_argument("--progress", dest="progress", action="store_true", default=None,
                   help="always show the progress bar (default: only on a terminal)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="never show it")


class DeprecatedAlias(argparse.Action):
    """A flag with an old name that still works: the old name stores the value and says, in one
    line on stderr, which name to use (``deprecated``: the old option strings; ``replacement``: the
    name to use, when it is another action's, the old name hidden from the help)."""

    def __init__(self, option_strings, dest, deprecated: tuple[str, ...] = (), replacement: str | None = None,
                 **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        self.deprecated, self.replacement = deprecated, replacement

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string in self.deprecated:
            current = self.replacement or next(o for o in self.option_strings if o not in self.deprecated)
            print(f"{parser.prog}: note: {option_string} is deprecated; use {current}", file=sys.stderr)
        setattr(namespace, self.dest, values)
