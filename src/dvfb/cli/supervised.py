"""``dvfb supervised``: the supervised reference of a task, trained and evaluated."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb import envs
from dvfb.cli.common import DEFAULT_PRESET, Formatter, progress_flag
from dvfb.core.config import add_arguments, merge, overrides_from_args
from dvfb.runs.layout import PretrainRun
from dvfb.runs.presets import PRESETS, preset_config
from dvfb.runs.run_config import run_config_class
from dvfb.workflows.pretrain import pretrain
from dvfb.workflows.zeroshot import zeroshot

AGENT = "supervised"


def supervised_config(args: argparse.Namespace):
    """The run config of ``dvfb supervised``: the preset, the flags, and the task's domain."""
    if args.task not in envs.TASKS:
        envs.make(args.task)  # one line listing the valid names
    overrides = overrides_from_args(args, run_config_class(AGENT))
    overrides["domain"] = envs.TASKS[args.task].domain
    overrides["supervised"] = {"task": args.task}
    return merge(preset_config(args.preset, AGENT), overrides)


def cmd_supervised(args: argparse.Namespace) -> int:
    config = supervised_config(args)
    run_dir = Path(args.run_dir) if args.run_dir else Path("runs") / f"{AGENT}_{args.task}_{config.preset}_s{config.seed}"
    run = pretrain(config, run_dir, resume=args.resume, overwrite=args.overwrite, progress=args.progress,
                   command=args.command_line)
    out = PretrainRun.open(run.path).zeroshot_result(args.task, config.frames)
    if out.exists():
        print(f"supervised reference {run.path}: already evaluated ({out})")
        return 0
    result = zeroshot(run.path, args.task, progress=args.progress)
    print(f"supervised reference {run.path}: {args.task} return {result['mean_return']:.1f} "
          f"± {result['std_return']:.1f} over {result['eval_episodes']} episodes ({out})")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "supervised", help="the supervised reference: DDPG from scratch on a task's reward, then evaluated",
        formatter_class=Formatter,
        description="The reference of the normalised scores (docs/reports.md): the DDPG core trained from "
                    "scratch, online, on the task's own reward for --frames steps (the budget of the "
                    "reward-free rows it is compared with), then --inference.eval-episodes mean-action "
                    "episodes on the task, written to RUN/zeroshot/<task>.json. It is a run like a "
                    "pre-training run (checkpoints, --resume, sweeps: agent 'supervised').")
    p.add_argument("--task", required=True, help="the task (its domain follows)")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=PRESETS, help="base configuration (default: %(default)s)")
    p.add_argument("--run-dir", default=None, help="run directory (default: runs/supervised_<task>_<preset>_s<seed>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its latest checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    progress_flag(p)
    add_arguments(p, run_config_class(AGENT), defaults=preset_config(DEFAULT_PRESET, AGENT),
                  skip=("preset", "agent", "domain", "supervised"))
    p.set_defaults(func=cmd_supervised)
