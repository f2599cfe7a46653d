"""``dvfb pretrain``: reward-free pre-training."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb.agents import agent_names
from dvfb.cli.common import (DEFAULT_PRESET, Formatter, default_run_dir, member_run_dirs, pretrain_config,
                             progress_flag, seed_list)
from dvfb.core.config import add_arguments
from dvfb.runs.presets import PRESETS, preset_config
from dvfb.runs.run_config import run_config_class
from dvfb.workflows.pretrain import pretrain


def cmd_pretrain(args: argparse.Namespace) -> int:
    config = pretrain_config(args)
    if args.seeds is not None:
        runs = pretrain(config, member_run_dirs(config, args.run_dir, args.seeds), seeds=args.seeds,
                        resume=args.resume, overwrite=args.overwrite, progress=args.progress, command=args.command_line)
        for run in runs:
            print(f"pre-training finished: {run.path}")
        return 0
    run_dir = Path(args.run_dir) if args.run_dir else default_run_dir(config)
    run = pretrain(config, run_dir, resume=args.resume, overwrite=args.overwrite,
                   progress=args.progress, command=args.command_line)
    print(f"pre-training finished: {run.path}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "pretrain", help="reward-free pre-training", formatter_class=Formatter,
        description="Reward-free online pre-training (docs/methods.md). Defaults shown are those of the "
                    f"{DEFAULT_PRESET!r} preset for --agent {agent}; --preset paper gives the spec's values "
                    "(hidden 1024, batch 1024, 2M frames), --preset code the authors' constants. The config "
                    "sections depend on the method: `dvfb pretrain --agent NAME --help` shows its flags.")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=PRESETS, help="base configuration (default: %(default)s)")
    p.add_argument("--run-dir", default=None, help="run directory (default: runs/<agent>_<domain>_<preset>_s<seed>)")
    p.add_argument("--seeds", type=seed_list, default=None,
                   help="train one member per seed in lockstep in this process, each in its own run directory "
                        "(--run-dir with {seed} in it, default: each seed's default); --seed is then unused "
                        "(docs/members.md)")
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its latest checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    progress_flag(p)
    p.add_argument("--agent", default=agent, choices=agent_names(), help="method (default: %(default)s)")
    add_arguments(p, run_config_class(agent), defaults=preset_config(DEFAULT_PRESET, agent), skip=("preset", "agent"))
    p.set_defaults(func=cmd_pretrain)
