#!/usr/bin/env python
"""Zero-shot returns of groups of runs side by side: mean ± std over seeds per task and of the
task average (docs/results/crosscheck_walker.md).

A group is ``LABEL=GLOB``: the directories that GLOB matches are its seeds. A directory is either
a dvfb pre-training run (``zeroshot/<task>.json``, its ``mean_return``) or the output directory of
the cross-implementation harness that trains the authors' agent (``zeroshot_<task>.json``, its
``mean``), or a ``dvfb random-policy --output`` file (one row of per-task means). Each seed's score on a task is the mean return of its evaluation episodes; a seed's
average is the mean over the tasks; the spread is the sample standard deviation over seeds
(ddof = 1), as in ``dvfb report``. Every task must be present for every seed.

With ``--metrics`` it prints pre-training metrics instead: for each group, the mean over seeds of
each metric every ``--every`` frames, read from a dvfb run's ``metrics/train.jsonl`` (the mean over
the updates of the last 1000 frames) or from the harness's ``log.txt`` (the values of the last
update before that frame), under dvfb's names (``METRIC_NAMES`` maps the harness's); with ``--window FIRST:LAST``, each seed's
mean of each metric over the logged frames in that range.

Usage: python scripts/crosscheck_table.py --tasks walker_stand,walker_walk,walker_run,walker_flip \
           "authors=sweeps/crosscheck/authors_walker_s?" "dvfb code=sweeps/crosscheck/dvfb_code_walker_s?"
       python scripts/crosscheck_table.py --metrics ortho_loss,rnd_reward [--window 11000:20000] "authors=..." "dvfb=..."
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np


def read_result(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SystemExit(f"crosscheck_table: cannot read {path}: {exc}") from exc


def seed_scores(run: Path, tasks: list[str]) -> list[float]:
    try:
        return _seed_scores(run, tasks)
    except (KeyError, TypeError, ValueError) as exc:
        raise SystemExit(f"crosscheck_table: {run} is not a dvfb run, a harness output or a random-policy "
                         f"file ({exc!r})") from exc


def _seed_scores(run: Path, tasks: list[str]) -> list[float]:
    if run.is_file():  # a `dvfb random-policy --output` file: one "seed"
        results = read_result(run)["tasks"]
        missing = [t for t in tasks if t not in results]
        if missing:
            raise SystemExit(f"crosscheck_table: {run} has no result for {', '.join(missing)}")
        return [float(results[t]["mean_return"]) for t in tasks]
    scores = []
    for task in tasks:
        dvfb_file, harness_file = run / "zeroshot" / f"{task}.json", run / f"zeroshot_{task}.json"
        if dvfb_file.is_file():
            scores.append(float(read_result(dvfb_file)["mean_return"]))
        elif harness_file.is_file():
            scores.append(float(read_result(harness_file)["mean"]))
        else:
            raise SystemExit(f"crosscheck_table: {run} has no zero-shot result for {task}")
    return scores


# The harness's metric names (the authors' agent's) -> dvfb's for the same quantity.
METRIC_NAMES = {"fb_loss": "fb_total", "orth_loss": "ortho_loss", "critic_loss": "fb_q_loss",
                "intinsic_critic_loss": "exploration_critic_loss", "actor_loss": "actor_loss", "rnd_loss": "rnd_loss",
                "intr_reward1": "rnd_reward", "intr_pbe_reward": "ce_reward", "intr_reward": "intrinsic_reward"}


def run_metrics(run: Path) -> dict[int, dict[str, float]]:
    """Pre-training metrics by frame, under dvfb's names."""
    jsonl, log = run / "metrics" / "train.jsonl", run / "log.txt"
    if jsonl.is_file():
        rows = [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]
        return {int(r["step"]): {k: float(v) for k, v in r.items() if k != "step"} for r in rows}
    if log.is_file():
        out = {}
        for line in log.read_text().splitlines():
            words = line.split()
            if len(words) > 1 and words[0] == "frames":
                pairs = dict(zip(words[0::2], words[1::2]))
                out[int(pairs["frames"])] = {METRIC_NAMES[k]: float(v) for k, v in pairs.items() if k in METRIC_NAMES}
        return out
    raise SystemExit(f"crosscheck_table: {run} has neither metrics/train.jsonl nor log.txt")


def print_metrics(groups: list[tuple[str, list[Path]]], names: list[str], every: int) -> None:
    per_group = [(label, [run_metrics(r) for r in runs]) for label, runs in groups]
    frames = sorted(set.intersection(*(set(m) for _, ms in per_group for m in ms)))
    frames = [f for f in frames if f % every == 0]
    for name in names:
        print(f"\n{name} (mean over seeds)\n")
        print("| frames | " + " | ".join(label for label, _ in per_group) + " |")
        print("|---:|" + "---:|" * len(per_group))
        for f in frames:
            cells = []
            for _, ms in per_group:
                values = [m[f][name] for m in ms if name in m[f]]
                cells.append(f"{np.mean(values):.4g}" if values else "-")
            print(f"| {f} | " + " | ".join(cells) + " |")


def print_window(groups: list[tuple[str, list[Path]]], names: list[str], first: int, last: int) -> None:
    """Per seed, the mean of each metric over the logged frames in [first, last]."""
    print(f"| runs | metric | per-seed means over frames {first}-{last} |")
    print("|---|---|---|")
    for label, runs in groups:
        metrics = [run_metrics(r) for r in runs]
        for name in names:
            means = []
            for m in metrics:
                values = [row[name] for f, row in sorted(m.items()) if first <= f <= last and name in row]
                means.append(f"{np.mean(values):.3g}" if values else "-")  # "-": not logged (e.g. FB's RND)
            print(f"| {label} | {name} | {', '.join(means)} |")


def cell(values: np.ndarray) -> str:
    if len(values) < 2:
        return f"{values.mean():.1f}"
    return f"{values.mean():.1f} ± {values.std(ddof=1):.1f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("groups", nargs="+", help="LABEL=GLOB: the run directories of one row")
    parser.add_argument("--tasks", help="comma-separated task names (the returns table)")
    parser.add_argument("--metrics", help="comma-separated dvfb metric names (the pre-training metrics table)")
    parser.add_argument("--every", type=int, default=5000, help="--metrics: frames between rows")
    parser.add_argument("--window", help="--metrics: FIRST:LAST, print each seed's mean over these frames instead")
    args = parser.parse_args(argv)
    groups = []
    for group in args.groups:
        label, sep, pattern = group.partition("=")
        if not sep:
            parser.error(f"{group!r} is not LABEL=GLOB")
        runs = sorted(Path(p) for p in glob.glob(pattern))
        if not runs:
            raise SystemExit(f"crosscheck_table: {pattern!r} matches no directory")
        groups.append((label, runs))
    if args.metrics:
        if args.window:
            first, _, last = args.window.partition(":")
            print_window(groups, args.metrics.split(","), int(first), int(last))
        else:
            print_metrics(groups, args.metrics.split(","), args.every)
        return 0
    if not args.tasks:
        parser.error("give --tasks (returns) or --metrics")
    tasks = args.tasks.split(",")
    # Every result is read before anything is printed: a bad directory prints one line only.
    tables = [(label, np.array([seed_scores(run, tasks) for run in runs])) for label, runs in groups]  # (seeds, tasks)
    print("| runs | seeds | " + " | ".join(t.split("_", 1)[-1] for t in tasks) + " | average | per-seed averages |")
    print("|---|---:|" + "---:|" * (len(tasks) + 2))
    for label, table in tables:
        averages = table.mean(axis=1)
        cells = [cell(table[:, i]) for i in range(len(tasks))]
        print(f"| {label} | {len(table)} | " + " | ".join(cells) + f" | {cell(averages)} | "
              + ", ".join(f"{a:.1f}" for a in averages) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
