"""``dvfb sweep run`` and ``dvfb sweep status``: grids of runs (:mod:`dvfb.sweep`; README "Sweeps",
docs/sweeps.md).

``dvfb sweep run [FILE] [--dir DIR] [sweep options] [config flags]``: the sweep options are the
fields of :class:`~dvfb.sweep.spec.SweepConfig` (``--agents dvfb fb --seeds 0 1 2
--executor slurm --slurm.pretrain.gpus 1 ...``); the config flags are those of ``dvfb pretrain``
(``--frames 50000 --fb.hidden-dim 32``), where comma-separated values make a grid axis
(``--exploration.alpha 1,5,50``). Command-line values override the file's.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from pathlib import Path

from dvfb.agents import agent_names
from dvfb.cli.common import Formatter
from dvfb.core.config import add_arguments, flag_name, overrides_from_args, to_dict
from dvfb.core.errors import ConfigError
from dvfb.runs.presets import preset_config
from dvfb.sweep import runner, spec
from dvfb.sweep.spec import SweepConfig
from dvfb.sweep.units import use_in_process

# argparse destination prefix of the pre-training config flags.
_OVERRIDE = "override:"


def _config_flags(group, cls: type, defaults, prefix: str = "", seen: set[str] | None = None) -> None:
    """One text option per pre-training config field of ``cls`` not seen yet; the sweep parses
    the text (a comma-separated list is a grid axis) with the field's type."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        if not prefix and f.name in spec.CELL_FIELDS:
            continue
        default = getattr(defaults, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            _config_flags(group, hints[f.name], default, f"{key}.", seen)
            continue
        if key in seen:
            continue
        seen.add(key)
        help_text = f.metadata.get("help", "")
        choices = f.metadata.get("choices")
        if choices:
            help_text += f" Choices: {', '.join(map(str, choices))}."
        group.add_argument(flag_name(key), dest=_OVERRIDE + key, default=argparse.SUPPRESS, metavar="V[,V...]",
                           help=f"{help_text} (default: {default!r})")


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", nargs="?", default=None,
                        help="sweep file (.toml or .json) with the fields below; command-line values override it")
    parser.add_argument("--dir", default=None, help="sweep directory (default: sweeps/<file name without "
                        "suffix>; without a file, required). Repeat the command to continue a sweep.")
    add_arguments(parser, SweepConfig, skip=("overrides",))
    group = parser.add_argument_group(
        "pre-training config flags of the cells (dvfb pretrain --help; defaults of the small preset; "
        "comma-separated values make a grid axis, e.g. --exploration.alpha 1,5,50; an option applies to "
        "the methods that have it)")
    seen: set[str] = set()
    for agent in agent_names():
        _config_flags(group, type(preset_config("small", agent)), preset_config("small", agent), seen=seen)


def config_from_args(args: argparse.Namespace):
    """The sweep directory and the sweep: defaults <- the stored sweep (a re-run without a file)
    <- the file <- the command line."""
    file = Path(args.file) if args.file else None
    if args.dir:
        path = Path(args.dir)
    elif file is not None:
        path = Path("sweeps") / file.stem
    else:
        raise ConfigError("give a sweep file or --dir DIR")
    file_data = spec.read_file(file) if file is not None else {}
    stored = path / spec.SWEEP_FILE
    base = to_dict(spec.load_stored(path)) if file is None and stored.is_file() else {}
    flag_overrides = {k[len(_OVERRIDE):]: v for k, v in vars(args).items() if k.startswith(_OVERRIDE)}
    config = spec.build(base, file_data, overrides_from_args(args, SweepConfig), flag_overrides)
    return path, config


def run_from_args(args: argparse.Namespace) -> int:
    path, config = config_from_args(args)
    only = getattr(args, "only", None) or None
    if getattr(args, "dry_run", False):
        for line in runner.dry_run(path, config, only):
            print(f"[sweep] {line}")
        return 0
    outcome = runner.run(path, config, only)
    print(f"[sweep] {len(outcome.done)} unit(s) run, {len(outcome.skipped)} already done, "
          f"{len(outcome.failed)} failed or not run; status: dvfb sweep status {path}")
    for reason in outcome.failed.values():
        print(f"[sweep] FAILED {reason}")
    return 1 if outcome.failed else 0


def status_from_args(args: argparse.Namespace) -> int:
    rows, warning = runner.status(Path(args.dir))
    print(runner.format_status(rows))
    if warning:
        print(f"dvfb sweep status: warning: {warning}", file=sys.stderr)
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    """A grid of runs through pre-train -> zero-shot -> fine-tune -> report (dvfb.sweep)."""
    use_in_process(args.entry_point)  # the debug executor's phases are dvfb commands run in this process

    return run_from_args(args)


def cmd_sweep_status(args: argparse.Namespace) -> int:
    """The table of a sweep's cells: done / running / queued / failed, frames and ETA."""
    return status_from_args(args)


def register(sub, agent: str) -> None:
    p = sub.add_parser("sweep", help="methods x domains x seeds: pre-train -> zero-shot -> fine-tune -> report",
                       formatter_class=Formatter,
                       description="Sweeps (README 'Sweeps', docs/sweeps.md): `dvfb sweep run FILE` runs a grid "
                                   "locally (default), on SLURM or in-process, resumably; `dvfb sweep status DIR` "
                                   "prints its cells.")
    sweep_sub = p.add_subparsers(dest="sweep_command", required=True, metavar="ACTION")
    q = sweep_sub.add_parser("run", help="run or continue a sweep", formatter_class=Formatter,
                             description="Run every phase of every cell that is not done yet: finished cells "
                                         "are skipped, interrupted ones resume from their checkpoints, failed "
                                         "ones are reported with their log and do not stop the others. Exit "
                                         "status 1 when a unit failed.")
    add_run_arguments(q)
    q.add_argument("--only", nargs="+", default=None, metavar="PATTERN",
                   help="run only the cells whose names match one of these shell-style patterns this time, e.g. "
                        "'*_walker_*' (the others wait for a later run; the report waits until every cell is done)")
    q.add_argument("--dry-run", action="store_true",
                   help="build and check every cell's config (the checks of a real run) and print the cells, jobs "
                        "and units it would run, and the pre-training commands; creates, runs and submits nothing")
    q.set_defaults(func=cmd_sweep)
    q = sweep_sub.add_parser("status", help="table of the cells of a sweep",
                             description="Each cell's state (done / running / queued / failed / stopped), "
                                         "pre-training frames, ETA of a running pre-training, and the reason "
                                         "and log of a failure.")
    q.add_argument("dir", help="sweep directory")
    q.set_defaults(func=cmd_sweep_status)
