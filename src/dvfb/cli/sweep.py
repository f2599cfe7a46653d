"""``dvfb sweep run`` and ``dvfb sweep status``: grids of runs (dvfb.sweep)."""

from __future__ import annotations

import argparse

from dvfb.cli.common import Formatter

def cmd_sweep(args: argparse.Namespace) -> int:
    """A grid of runs through pre-train -> zero-shot -> fine-tune -> report (dvfb.sweep)."""
    from dvfb.sweep.cli import run_from_args
    from dvfb.sweep.units import use_in_process

    use_in_process(args.entry_point)  # the debug executor's phases are dvfb commands run in this process

    return run_from_args(args)


def cmd_sweep_status(args: argparse.Namespace) -> int:
    """The table of a sweep's cells: done / running / queued / failed, frames and ETA."""
    from dvfb.sweep.cli import status_from_args

    return status_from_args(args)


def register(sub, agent: str) -> None:
    from dvfb.sweep.cli import add_run_arguments as add_sweep_run_arguments

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
    add_sweep_run_arguments(q)
    q.set_defaults(func=cmd_sweep)
    q = sweep_sub.add_parser("status", help="table of the cells of a sweep",
                             description="Each cell's state (done / running / queued / failed / stopped), "
                                         "pre-training frames, ETA of a running pre-training, and the reason "
                                         "and log of a failure.")
    q.add_argument("dir", help="sweep directory")
    q.set_defaults(func=cmd_sweep_status)
