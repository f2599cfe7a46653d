"""``dvfb zeroshot``: the skill of a task by the run's zero-shot protocol, and its evaluation; of a
run directory, or of an exported model (docs/sharing.md, "Evaluate")."""

from __future__ import annotations

import argparse

from dvfb.cli.common import (DeprecatedAlias, Formatter, add_protocol_arguments, add_snapshot_and_seed, eval_dir_flag,
                             evaluated, parse_goal, progress_flag, protocol_overrides, torch_threads_flag)
from dvfb.core.errors import ConfigError
from dvfb.protocols import FINETUNERS
from dvfb.runs.layout import FinetuneRun
from dvfb.workflows.finetune import finetune
from dvfb.workflows.resources import evaluation_tasks, open_run
from dvfb.workflows.zeroshot import zeroshot

# zeroshot --protocol online_inference: its options, named after what they configure; --finetune.*
# (their first name: the protocol runs on the fine-tuning loop) still works, with a note.
ONLINE, ONLINE_OLD = "online-inference", "finetune"


def _online_options(args: argparse.Namespace) -> dict:
    return protocol_overrides(args, "finetune", online=True, prefix=ONLINE)


def cmd_zeroshot(args: argparse.Namespace) -> int:
    if args.protocol is not None:
        return _online(args)

    if args.resume:
        raise ConfigError("--resume continues a zero-shot protocol that runs in the task: pass --protocol with it")
    if _online_options(args):
        raise ConfigError(f"--{ONLINE}.* options configure --protocol online_inference; pass it, or leave them out")
    with evaluated(args.run, args.eval_dir, args.command_line) as (runs, inference_data, exported):
        return _zeroshot(args, runs, inference_data, exported)


def _zeroshot(args: argparse.Namespace, runs: list[str], inference_data, exported: bool) -> int:
    group = len(runs) > 1
    first_run = open_run(runs[0], args.torch_threads)
    config = first_run.config
    for other in runs[1:]:
        open_run(other, args.torch_threads)  # names a missing or broken run before any work
    # Every task is checked before the first is run: a bad second name must not leave a first result.
    tasks = evaluation_tasks(config, args.task)
    inference = protocol_overrides(args, "inference")
    goal = parse_goal(args.goal) if args.goal else None
    options = dict(snapshot=args.snapshot, inference=inference, seed=args.seed, skill_source=args.skill_source,
                   reward_fn=args.reward_fn, goal=goal, overwrite=args.overwrite, progress=args.progress,
                   dataset=args.dataset, torch_threads=args.torch_threads, inference_data=inference_data)
    rows = []
    for task in tasks:
        results = zeroshot(runs if group else runs[0], task, skip_existing=args.skip_existing, **options)
        results = results if group else [results]
        for run, result in zip(runs, results):
            if result is not None:
                rows.append((task, run, result["mean_return"], result["std_return"], result["eval_episodes"],
                             result.get("success_rate")))
    with_success = any(row[5] is not None for row in rows)
    print(f"{'task':<36} " + (f"{'run':<32} " if group else "") + f"{'return':>9} {'std':>8} {'episodes':>9}"
          + (f" {'success':>8}" if with_success else ""))
    for task, run, mean, std, n, success in rows:
        print(f"{task:<36} " + (f"{run:<32} " if group else "") + f"{mean:9.1f} {std:8.1f} {n:9d}"
              + (f" {success:8.2f}" if success is not None else ""))
    if exported:  # say where its results are: not beside its own files
        print(f"results: {first_run.zeroshot_dir}")
    return 0


def _online(args: argparse.Namespace) -> int:
    """A zero-shot protocol that infers the task from interaction alone (``online_inference``): it
    runs in the task on the fine-tuning loop (its budget, resume and evaluations), under
    ``RUN/finetune/<task>.<protocol>/``."""
    cls = FINETUNERS.get(args.protocol)
    if cls is None or cls.infers_skill:
        choices = ", ".join(name for name, c in FINETUNERS.items() if not c.infers_skill)
        raise ConfigError(f"--protocol {args.protocol} is not a zero-shot protocol that runs in the task; choose "
                          f"one of {choices}")
    for name, flag in (("skill_source", "--skill-source"), ("goal", "--goal"), ("reward_fn", "--reward-fn"),
                       ("dataset", "--dataset"), ("skip_existing", "--skip-existing")):
        if getattr(args, name) not in (None, False, "rewards"):
            raise ConfigError(f"{flag} does not apply to --protocol {args.protocol} (it infers the task from the "
                              "rewards it observes)")
    if len(args.task) != 1 or args.task[0] == "all":
        raise ConfigError(f"--protocol {args.protocol} runs in one task at a time: pass one --task")
    if protocol_overrides(args, "inference"):
        raise ConfigError(f"--inference.* options do not apply to --protocol {args.protocol}: its options are "
                          f"--{ONLINE}.*")
    with evaluated(args.run, args.eval_dir, args.command_line) as (runs, _data, _exported):
        return _online_runs(args, runs)


def _online_runs(args: argparse.Namespace, runs: list[str]) -> int:
    many = len(runs) > 1
    done = finetune(runs if many else runs[0], args.task[0], snapshot=args.snapshot, seed=args.seed,
                    finetune=_online_options(args), resume=args.resume, overwrite=args.overwrite,
                    progress=args.progress, protocol=args.protocol, torch_threads=args.torch_threads)
    for run in done if many else [done]:
        curve = FinetuneRun(run.path, None).curve()
        returns = " ".join(f"{e['return']:.1f}" for e in curve.episodes or [])
        print(f"{args.protocol} finished: {run.path}")
        print(f"episode returns: {returns}")
        print(f"final z: {curve.curve[-1]['mean_return']:.1f} over {len(curve.curve[-1].get('returns', []))} "
              f"mean-action episodes")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser("zeroshot", help="the skill of a task by the method's zero-shot protocol, evaluated", formatter_class=Formatter,
                       description="Zero-shot by the method's registered protocol (docs/methods.md, \"Protocols\"): "
                                   "the FB family infers z_r from reward-labelled steps (or a reward function or "
                                   "a goal), the skill-discovery methods select the best prior skill over the "
                                   "same steps, methods without skills use their one policy; then mean-action "
                                   "evaluation episodes. Defaults come from the run's config, which its preset "
                                   "made (shown by preset below). An exported model (dvfb export) is evaluated in "
                                   "a run directory made from it, EXPORT.eval beside it unless --eval-dir says "
                                   "otherwise; its own files are never written (docs/sharing.md, \"Evaluate\").")
    p.add_argument("run", nargs="+", help="pre-training run directory, or an exported model's directory; several: the "
                                          "members of a group (one method and configuration, seeds aside), evaluated "
                                          "together with batched actor forward passes (docs/members.md)")
    p.add_argument("--task", nargs="+", required=True, help="task name(s) of the run's domain, or 'all'")
    add_snapshot_and_seed(p, "task seed")
    p.add_argument("--skill-source", "--z-source", dest="skill_source", default="rewards", action=DeprecatedAlias,
                   deprecated=("--z-source",),
                   choices=("rewards", "reward_fn", "dataset", "goal"),
                   help="where the task's skill comes from: interaction with the task (every method), a reward "
                        "function over the run's replay states (an exported model's inference data), a dataset "
                        "relabelled for the task from its physics states (an exported model's inference data when "
                        "no --dataset is given), or a goal (methods that infer skills); --z-source is its "
                        "deprecated old name (default: %(default)s)")
    p.add_argument("--dataset", default=None, help="--skill-source dataset: the dataset directory (default: the one "
                                                   "an offline run trained on)")
    p.add_argument("--reward-fn", default=None, help="module:function or file.py:function mapping next_obs (N, O) to rewards")
    p.add_argument("--goal", default=None, help="goal observation: a .npy file or comma-separated numbers")
    p.add_argument("--overwrite", action="store_true", help="replace an existing result file")
    p.add_argument("--skip-existing", action="store_true",
                   help="leave out the runs that already have a task's result (a group evaluates the others) "
                        "instead of stopping with an error")
    p.add_argument("--protocol", default=None,
                   help="online_inference: infer the task from interaction alone (no labelled data; a UCB or "
                        "Thompson-sampling bandit over z), recording every episode's return, then evaluate the "
                        f"final z; runs under RUN/finetune/<task>.<protocol>/ and takes --{ONLINE}.* options "
                        "(default: the method's own protocol)")
    p.add_argument("--resume", action="store_true", help="with --protocol: continue from its latest checkpoint")
    eval_dir_flag(p)
    progress_flag(p)
    torch_threads_flag(p)
    add_protocol_arguments(p, "inference")
    add_protocol_arguments(p, "finetune", online=True, prefix=ONLINE, deprecated_prefix=ONLINE_OLD)
    p.set_defaults(func=cmd_zeroshot)
