"""The ``dvfb`` command line, one module per command: tasks and agents (:mod:`~dvfb.cli.info`), pretrain,
zeroshot, finetune, supervised (the reference), random-policy, demo, sweep, status, report, the analyses
(analyze-value, analyze-exploration), bands (the reference bands of dvfb status), video, dataset (export and relabel), export and push (:mod:`~dvfb.cli.share`).

Every option of the typed run configuration is a flag (nested fields as ``--fb.hidden-dim``), shown
with its default in ``--help``. Errors caused by input (unknown task, bad run directory, mismatched
checkpoint, NaN loss) print one line and exit with status 2; nothing existing is overwritten unless
``--overwrite`` is given.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys

from dvfb.core.version import __version__
from dvfb.agents import agent_names
from dvfb.cli import (analyze, bands, dataset, demo, finetune, info, pretrain, random_policy, report, share, status,
                      supervised, sweep, video, zeroshot)
from dvfb.cli.common import Formatter, Parser, unknown_option_message
from dvfb.core.errors import DvfbError, RunInterrupted
from dvfb.training.progress import progress_interval

# The order of `dvfb --help`.
COMMANDS = (info, pretrain, zeroshot, finetune, supervised, random_policy, demo, sweep, status, bands, report, analyze,
            video, dataset, share)


def build_parser(agent: str = "dvfb") -> argparse.ArgumentParser:
    """The parser; ``pretrain``'s config flags are those of ``agent`` (read from ``--agent`` first)."""
    parser = Parser(prog="dvfb", description="Online unsupervised zero-shot RL: DVFB, FB and "
                                     "baselines (`dvfb agents`).", formatter_class=Formatter)
    parser.add_argument("--version", action="version", version=f"dvfb {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    # The entry point itself, for commands that run other dvfb commands in-process (sweeps' debug
    # executor); handed down instead of imported, since the commands stand below this module.
    parser.set_defaults(entry_point=main)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.register(sub, agent)
    # Global flags are accepted after the sub-command too (`dvfb pretrain ... -v`).
    for subparser in sub.choices.values():
        subparser.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                               help="log progress messages")
    parser.set_defaults(commands=sub.choices)  # the command's own parser names a word none of its flags took
    return parser


def _requested_agent(argv: list[str]) -> str:
    """The value of ``pretrain --agent`` (which decides the config flags), before the full parse."""
    if "pretrain" not in argv:
        return "dvfb"
    rest = argv[argv.index("pretrain") + 1:]
    for i, token in enumerate(rest):
        value = None
        if token == "--agent" and i + 1 < len(rest):
            value = rest[i + 1]
        elif token.startswith("--agent="):
            value = token.split("=", 1)[1]
        if value is not None:
            return value if value in agent_names() else "dvfb"  # argparse names a bad choice
    return "dvfb"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_requested_agent(argv))
    args, extra = parser.parse_known_args(argv)
    if extra:
        args.commands[args.command].error(unknown_option_message(args, extra))
    # What a run's meta.json records as its command: this call's, also when it runs in-process (a
    # sweep's debug executor, the tests), where sys.argv is the host program's.
    args.command_line = ["dvfb", *argv]
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        # A bad DVFB_PROGRESS_SECONDS is bad input: refused before the command creates anything.
        progress_interval()
        return args.func(args)
    except RunInterrupted as exc:
        print(f"dvfb {args.command}: {exc}", file=sys.stderr)
        return 128 + exc.signum
    except DvfbError as exc:
        print(f"dvfb {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dvfb {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader stopped reading (dvfb status RUN | head): stop quietly, as Unix tools do; stdout
        # goes to /dev/null so that the interpreter's last flush does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except OSError as exc:
        # A disk error no writer named itself (a read-only or full disk, a permission): one line
        # naming the path, as for any other bad input, not a traceback.
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"dvfb {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
