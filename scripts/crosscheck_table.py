#!/usr/bin/env python
"""Zero-shot returns of groups of runs side by side: mean ± std over seeds per task and of the
task average (docs/results/crosscheck_walker.md).

A group is ``LABEL=GLOB``: the directories that GLOB matches are its seeds. A directory is either
a dvfb pre-training run (``zeroshot/<task>.json``, its ``mean_return``) or the output directory of
the cross-implementation harness that trains the authors' agent (``zeroshot_<task>.json``, its
``mean``). Each seed's score on a task is the mean return of its evaluation episodes; a seed's
average is the mean over the tasks; the spread is the sample standard deviation over seeds
(ddof = 1), as in ``dvfb report``. Every task must be present for every seed.

Usage: python scripts/crosscheck_table.py --tasks walker_stand,walker_walk,walker_run,walker_flip \
           "authors=sweeps/crosscheck/authors_walker_s?" "dvfb code=sweeps/crosscheck/dvfb_code_walker_s?"
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np


def seed_scores(run: Path, tasks: list[str]) -> list[float]:
    scores = []
    for task in tasks:
        dvfb_file, harness_file = run / "zeroshot" / f"{task}.json", run / f"zeroshot_{task}.json"
        if dvfb_file.is_file():
            scores.append(float(json.loads(dvfb_file.read_text())["mean_return"]))
        elif harness_file.is_file():
            scores.append(float(json.loads(harness_file.read_text())["mean"]))
        else:
            raise SystemExit(f"crosscheck_table: {run} has no zero-shot result for {task}")
    return scores


def cell(values: np.ndarray) -> str:
    if len(values) < 2:
        return f"{values.mean():.1f}"
    return f"{values.mean():.1f} ± {values.std(ddof=1):.1f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("groups", nargs="+", help="LABEL=GLOB: the run directories of one row")
    parser.add_argument("--tasks", required=True, help="comma-separated task names")
    args = parser.parse_args(argv)
    tasks = args.tasks.split(",")
    print("| runs | seeds | " + " | ".join(t.split("_", 1)[-1] for t in tasks) + " | average | per-seed averages |")
    print("|---|---:|" + "---:|" * (len(tasks) + 2))
    for group in args.groups:
        label, sep, pattern = group.partition("=")
        if not sep:
            parser.error(f"{group!r} is not LABEL=GLOB")
        runs = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_dir())
        if not runs:
            raise SystemExit(f"crosscheck_table: {pattern!r} matches no directory")
        table = np.array([seed_scores(run, tasks) for run in runs])  # (seeds, tasks)
        averages = table.mean(axis=1)
        cells = [cell(table[:, i]) for i in range(len(tasks))]
        print(f"| {label} | {len(runs)} | " + " | ".join(cells) + f" | {cell(averages)} | "
              + ", ".join(f"{a:.1f}" for a in averages) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
