"""``dvfb random-policy``: the uniform-random floor of a domain's tasks."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb import envs
from dvfb.cli.common import integer, seed_value, torch_threads_flag
from dvfb.core.errors import ConfigError
from dvfb.runs import check_writable, write_json_atomic
from dvfb.workflows.resources import use_threads
from dvfb.workflows.zeroshot import random_policy_evaluation


def cmd_random_policy(args: argparse.Namespace) -> int:
    """Returns of a uniform-random policy on every task of a domain (the table's floor)."""
    use_threads(args.torch_threads)
    envs.check_domain(args.domain)
    output = Path(args.output) if args.output else None
    if output is not None and output.is_dir():
        raise ConfigError(f"--output {output} is a directory; give a file name (e.g. {output / 'random.json'})")
    if output is not None and output.exists() and not args.overwrite:
        raise ConfigError(f"{output} exists; pass --overwrite to replace it")
    if output is not None:
        check_writable(output.parent)  # a read-only or full disk fails now, not after the episodes
    results = {}
    for task in envs.tasks_of_domain(args.domain):
        results[task] = random_policy_evaluation(task, args.episodes, seed=args.seed).summary()
        success = results[task].get("success_rate")
        print(f"{task:<36} {results[task]['mean_return']:9.1f} {results[task]['std_return']:8.1f}"
              + (f"  success {success:.2f}" if success is not None else ""))
    if output is not None:
        output.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(output, {"agent": "random", "domain": args.domain, "seed": args.seed,
                                   "episodes": args.episodes, "tasks": results})
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser("random-policy", help="returns of a uniform-random policy on a domain's tasks",
                       description="Evaluate a uniform-random policy on every task of a domain.")
    p.add_argument("--domain", required=True, help="domain name")
    p.add_argument("--episodes", type=integer(1), default=10, help="episodes per task (default: %(default)s)")
    p.add_argument("--seed", type=seed_value, default=0, help="(default: %(default)s)")
    p.add_argument("--output", default=None, help="write the returns to this JSON file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    torch_threads_flag(p, on_run=False)
    p.set_defaults(func=cmd_random_policy)
