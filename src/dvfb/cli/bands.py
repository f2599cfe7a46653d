"""``dvfb bands``: reference bands from a study's results, for the verdicts of ``dvfb status``."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb.analysis.bands import make_bands, write_bands
from dvfb.cli.common import Formatter
from dvfb.core.errors import ConfigError


def cmd_bands(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ConfigError(f"{out} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise ConfigError(f"--out {out} is a directory; give the bands file's path")
    bands = make_bands(args.runs, args.random or ())
    write_bands(bands, out)
    cells = {(b["method"], b["domain"]) for b in bands["bands"]}
    print(f"{len(bands['bands'])} bands ({len(cells)} method x domain pairs) and {len(bands['random'])} random-policy "
          f"bands written to {out}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "bands", help="reference bands (per method, domain, task, snapshot: seeds' mean, min, max) from a study",
        formatter_class=Formatter,
        description="Read the zero-shot results of the pre-training runs under RUN_DIR (every snapshot's, "
                    "RUN/zeroshot/<task>[@<frames>].json) and the random-policy files, and write per method, domain, "
                    "preset, budget, task and snapshot the seeds' mean, minimum and maximum, and per task the random "
                    "policy's episodes: the bands `dvfb status` reads a run's evaluations against (docs/health.md). "
                    "The package's own come from docs/results/cpu_100k.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories or directories containing runs")
    p.add_argument("--random", nargs="+", action="extend", default=None, metavar="FILE.json",
                   help="random-policy files (dvfb random-policy --output)")
    p.add_argument("--out", required=True, help="the bands file to write (JSON)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_bands)
