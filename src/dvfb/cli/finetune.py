"""``dvfb finetune``: fine-tuning by the method's registered fine-tuner."""

from __future__ import annotations

import argparse

from dvfb.cli.common import (Formatter, add_finetune_arguments, add_protocol_arguments, add_snapshot_and_seed,
                             progress_flag, protocol_overrides, torch_threads_flag)
from dvfb.core.config import add_arguments, overrides_from_args
from dvfb.runs.layout import FinetuneRun
from dvfb.runs.wandb_sink import LogConfig
from dvfb.workflows.finetune import finetune


def cmd_finetune(args: argparse.Namespace) -> int:
    options = dict(snapshot=args.snapshot, seed=args.seed, name=args.name,
                   inference=protocol_overrides(args, "inference"), finetune=protocol_overrides(args, "finetune"),
                   resume=args.resume, overwrite=args.overwrite, progress=args.progress, protocol=args.protocol,
                   log=overrides_from_args(args, LogConfig, prefix="log."), torch_threads=args.torch_threads)
    many = len(args.run) > 1
    runs = finetune(args.run if many else args.run[0], args.task, **options)
    runs = runs if many else [runs]
    for run in runs:
        summary = FinetuneRun(run.path, None).summary()
        print(f"fine-tuning finished: {run.path}")
        print(f"zero-shot return {summary.zero_shot_return:.1f} -> after {summary.frames} frames "
              f"{summary.final_return:.1f}")
        if summary.final_success_rate is not None:
            print(f"zero-shot success rate {summary.zero_shot_success_rate:.2f} -> after {summary.frames} "
                  f"frames {summary.final_success_rate:.2f}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser("finetune", help="fine-tune a pre-trained run on a task", formatter_class=Formatter,
                       description="Fine-tuning by the method family's protocol: dual-value (a fresh task critic, "
                                   "reward mapping and the skill value) for DVFB/FB, URLB's (pre-trained actor, "
                                   "fresh critic with the pre-trained trunk, extrinsic n-step reward, the "
                                   "selected skill) for the DDPG baselines. Defaults come from the run's config, "
                                   "which its preset made (shown by preset below); another fine-tuner chosen with "
                                   "--protocol starts from its own config's defaults. Each fine-tuner's "
                                   "--finetune.* options are listed under its name; an option the run's "
                                   "fine-tuner does not have is refused.")
    p.add_argument("run", nargs="+", help="pre-training run directory; several: the members of a group (one method "
                                          "and configuration, seeds aside), fine-tuned together in lockstep with "
                                          "batched updates and actions (docs/members.md)")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    add_snapshot_and_seed(p)
    p.add_argument("--name", default=None, help="name of the fine-tuning run under RUN/finetune/ (default: the task)")
    p.add_argument("--protocol", default=None,
                   help="another fine-tuner the method may use (FB family and SF: latent_search, test-time search "
                        "over z; online_inference, task inference from interaction alone); its --finetune.* options "
                        "then apply, those listed under its name (default: the method's own; a resumed run "
                        "keeps its own)")
    p.add_argument("--resume", action="store_true", help="continue from the latest fine-tuning checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing fine-tuning run")
    progress_flag(p)
    torch_threads_flag(p)
    add_protocol_arguments(p, "inference")
    add_finetune_arguments(p)

    group = p.add_argument_group("logging options (default: the pre-training run's)")
    add_arguments(group, LogConfig, prefix="log.")
    p.set_defaults(func=cmd_finetune)
