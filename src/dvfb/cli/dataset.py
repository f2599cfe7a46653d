"""``dvfb dataset``: a pre-training run's replay as an ExORL-layout dataset, and its relabelling."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb.cli.common import Formatter, progress_flag, torch_threads_flag
from dvfb.data.datasets import EPISODES_DIR, default_relabel_dir, describe, relabel
from dvfb.training.progress import progress_bars
from dvfb.workflows.dataset_export import default_export_dir, export_run
from dvfb.workflows.resources import use_threads


def cmd_export(args: argparse.Namespace) -> int:
    use_threads(args.torch_threads)
    info = export_run(args.run, args.out, progress=progress_bars(args.progress))
    out = Path(args.out) if args.out else default_export_dir(args.run)
    print(describe(info, out) + f"; episode files in {out / EPISODES_DIR}")
    return 0


def cmd_relabel(args: argparse.Namespace) -> int:
    use_threads(args.torch_threads)
    info = relabel(args.dataset, args.task, args.out, progress=progress_bars(args.progress))
    print(describe(info, args.out or default_relabel_dir(Path(args.dataset), args.task)))
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "dataset", help="export a run's replay as a dataset (ExORL layout); relabel it for another task",
        formatter_class=Formatter,
        description="Datasets made from dvfb's own pre-training runs (docs/methods.md, \"Datasets\"): one .npz "
                    "file per finished episode with ExORL's keys (observation, action, reward, discount, physics) "
                    "and a dataset.json. The run must have been pre-trained with --replay.record-physics true.")
    commands = p.add_subparsers(dest="dataset_command", required=True, metavar="SUBCOMMAND")
    export = commands.add_parser(
        "export", help="write a run's pre-training replay as a dataset", formatter_class=Formatter,
        description="Write the replay of a pre-training run (its final resume checkpoint) as one .npz file per "
                    "finished episode in OUT/buffer/ (the episode in progress, if any, is left out) plus "
                    "OUT/dataset.json. OUT must not exist or be empty.")
    export.add_argument("run", help="pre-training run directory (pre-trained with --replay.record-physics true)")
    export.add_argument("--out", default=None, help="output directory (default: RUN/dataset)")
    progress_flag(export)
    torch_threads_flag(export, on_run=False)
    export.set_defaults(func=cmd_export)
    relabel = commands.add_parser(
        "relabel", help="recompute a dataset's rewards for another task of its domain", formatter_class=Formatter,
        description="Recompute every step's reward from the stored physics states with TASK's own reward "
                    "function, exactly as TASK's environment computes it, and write the relabelled dataset to a "
                    "new directory (the source is never changed).")
    relabel.add_argument("dataset", help="dataset directory (from `dvfb dataset export` or an earlier relabel)")
    relabel.add_argument("--task", required=True, help="a task of the dataset's domain (see `dvfb tasks`)")
    relabel.add_argument("--out", default=None, help="output directory (default: DATASET_<task>, beside DATASET)")
    progress_flag(relabel)
    torch_threads_flag(relabel, on_run=False)
    relabel.set_defaults(func=cmd_relabel)
