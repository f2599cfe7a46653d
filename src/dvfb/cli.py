"""The ``dvfb`` command line: tasks, pretrain, zeroshot, finetune, demo, and the reports and analyses
(report, analyze-value, analyze-exploration, video).

Every option of the typed run configuration is a flag (nested fields as ``--fb.hidden-dim``), shown
with its default in ``--help``. Errors caused by input (unknown task, bad run directory, mismatched
checkpoint, NaN loss) print one line and exit with status 2; nothing existing is overwritten unless
``--overwrite`` is given.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

import numpy as np

from dvfb import __version__
from dvfb.config import add_arguments, merge, overrides_from_args
from dvfb.errors import ConfigError, DvfbError, RunInterrupted

DEFAULT_PRESET = "small"


class _Formatter(argparse.RawDescriptionHelpFormatter):
    pass


def _default_run_dir(config) -> Path:
    return Path("runs") / f"{config.agent}_{config.domain}_{config.preset}_s{config.seed}"


def _parse_goal(text: str) -> np.ndarray:
    path = Path(text)
    if path.suffix == ".npy":
        if not path.exists():
            raise ConfigError(f"goal file {path} does not exist")
        return np.load(path)
    try:
        return np.array([float(x) for x in text.split(",")], dtype=np.float32)
    except ValueError as exc:
        raise ConfigError(f"--goal must be a .npy file or comma-separated numbers, got {text!r}") from exc


# ---------------------------------------------------------------------------------------------
# Sub-commands


def cmd_tasks(args: argparse.Namespace) -> int:
    from dvfb import envs

    print(envs.format_task_table())
    return 0


def _pretrain_config(args: argparse.Namespace):
    from dvfb.workflows.config import preset_config, run_config_class

    base = preset_config(args.preset, args.agent)
    return merge(base, overrides_from_args(args, run_config_class(args.agent)))


def cmd_agents(args: argparse.Namespace) -> int:
    """The registered methods, from the registry."""
    from dvfb.agents import AGENTS

    rows = [(s.name, s.family, s.zero_shot, s.finetuner, ", ".join(s.sections)) for s in AGENTS.values()]
    header = ("agent", "family", "zero-shot", "fine-tuner", "config sections")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
    print()
    for spec in AGENTS.values():
        print(f"{spec.name}: {spec.summary}")
    return 0


def _protocol_classes(kind: str) -> list[type]:
    """The config classes of every registered zero-shot protocol (``inference``) or fine-tuner."""
    from dvfb.protocols import FINETUNERS, ZERO_SHOT_PROTOCOLS

    registry = ZERO_SHOT_PROTOCOLS if kind == "inference" else FINETUNERS
    classes: list[type] = []
    for protocol in registry.values():
        if protocol.config_cls not in classes:
            classes.append(protocol.config_cls)
    return classes


def _add_protocol_arguments(p: argparse.ArgumentParser, kind: str) -> None:
    """``--inference.*`` or ``--finetune.*`` flags: the union of the families' fields, each once.

    Which of them apply depends on the run's method; a flag its family lacks is an error naming
    the family's config class when the run is loaded.
    """
    seen: set[str] = set()
    for cls in _protocol_classes(kind):
        skip = tuple(f.name for f in dataclasses.fields(cls) if f.name in seen)
        if len(skip) < len(dataclasses.fields(cls)):
            group = p.add_argument_group(f"{kind} options ({cls.__name__})")
            add_arguments(group, cls, prefix=f"{kind}.", skip=skip)
        seen.update(f.name for f in dataclasses.fields(cls))


def _protocol_overrides(args: argparse.Namespace, kind: str) -> dict:
    out: dict = {}
    for cls in _protocol_classes(kind):
        out.update(overrides_from_args(args, cls, prefix=f"{kind}."))
    return out


def cmd_pretrain(args: argparse.Namespace) -> int:
    from dvfb.workflows.pretrain import pretrain

    config = _pretrain_config(args)
    run_dir = Path(args.run_dir) if args.run_dir else _default_run_dir(config)
    run = pretrain(config, run_dir, resume=args.resume, overwrite=args.overwrite,
                   progress=args.progress, command=sys.argv)
    print(f"pre-training finished: {run.path}")
    return 0


def cmd_zeroshot(args: argparse.Namespace) -> int:
    from dvfb import envs
    from dvfb.workflows.snapshots import open_pretrained_run
    from dvfb.workflows.zeroshot import zeroshot

    _run, config = open_pretrained_run(args.run)
    tasks = envs.tasks_of_domain(config.domain) if args.task == ["all"] else args.task
    inference = _protocol_overrides(args, "inference")
    goal = _parse_goal(args.goal) if args.goal else None
    rows = []
    for task in tasks:
        result = zeroshot(args.run, task, snapshot=args.snapshot, inference=inference, seed=args.seed,
                          skill_source=args.skill_source, reward_fn=args.reward_fn, goal=goal,
                          overwrite=args.overwrite, progress=args.progress)
        rows.append((task, result["mean_return"], result["std_return"], result["eval_episodes"],
                     result.get("success_rate")))
    with_success = any(row[4] is not None for row in rows)
    print(f"{'task':<36} {'return':>9} {'std':>8} {'episodes':>9}" + (f" {'success':>8}" if with_success else ""))
    for task, mean, std, n, success in rows:
        print(f"{task:<36} {mean:9.1f} {std:8.1f} {n:9d}" + (f" {success:8.2f}" if success is not None else ""))
    return 0


def cmd_finetune(args: argparse.Namespace) -> int:
    from dvfb.workflows.finetune import finetune

    run = finetune(args.run, args.task, snapshot=args.snapshot, seed=args.seed, name=args.name,
                   inference=_protocol_overrides(args, "inference"),
                   finetune=_protocol_overrides(args, "finetune"),
                   resume=args.resume, overwrite=args.overwrite, progress=args.progress)

    summary = json.loads((run.path / "finetune_summary.json").read_text())
    print(f"fine-tuning finished: {run.path}")
    print(f"zero-shot return {summary['zero_shot_return']:.1f} -> after {summary['frames']} frames "
          f"{summary['final_return']:.1f}")
    if "final_success_rate" in summary:
        print(f"zero-shot success rate {summary['zero_shot_success_rate']:.2f} -> after {summary['frames']} frames "
              f"{summary['final_success_rate']:.2f}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The bundled pre-trained DVFB walker zero-shot on its 4 tasks against a random policy, a GIF of
    one task, then a short live pre-training that shows the pipeline (docs: README, "Two commands")."""
    import shutil

    from dvfb import envs
    from dvfb.analysis.video import record_video
    from dvfb.errors import DvfbError
    from dvfb.workflows.config import preset_config
    from dvfb.workflows.pretrain import pretrain
    from dvfb.workflows.zeroshot import random_policy_return, zeroshot

    out = Path(args.out_dir)
    bundled = bundled_demo_run()
    agent_dir = out / "pretrained_dvfb_walker"
    provenance = json.loads((bundled / "provenance.json").read_text())
    if agent_dir.exists():
        shutil.rmtree(agent_dir)
    shutil.copytree(bundled, agent_dir)
    print(f"[demo] bundled agent: DVFB pre-trained on walker for {provenance['frames']} frames "
          f"({provenance['preset']} preset; how it was made: {agent_dir / 'provenance.json'})")
    inference = {"steps": args.inference_steps, "random_action_steps": args.inference_steps // 2,
                 "samples": args.inference_steps, "eval_episodes": args.eval_episodes}
    print(f"[demo] zero-shot: {args.inference_steps} reward-labelled steps per task, "
          f"{args.eval_episodes} evaluation episode(s); random policy: {args.eval_episodes} episode(s)")
    header = f"{'task':<24} {'DVFB zero-shot':>15} {'random policy':>14}"
    lines = [header, "-" * len(header)]
    for task in envs.tasks_of_domain("walker"):
        result = zeroshot(agent_dir, task, inference=inference, overwrite=True, progress=args.progress)
        random_return = float(np.mean(random_policy_return(task, args.eval_episodes, seed=0)))
        lines.append(f"{task:<24} {result['mean_return']:15.1f} {random_return:14.1f}")
    print("\n".join(lines))
    gif = out / f"{args.gif_task}.gif"
    try:
        video = record_video(agent_dir, args.gif_task, out=gif, max_steps=args.gif_steps, frame_skip=4,
                             height=160, width=200, overwrite=True)
        print(f"[demo] {video['path']}: zero-shot {args.gif_task}, {video['frames']} frames")
    except (DvfbError, RuntimeError) as exc:  # rendering needs OpenGL; the rest of the demo does not
        print(f"[demo] no GIF: {exc}")
    config = preset_config("small", agent="dvfb", domain="walker", frames=args.frames, seed=0,
                           seed_frames=min(1000, args.frames // 2), checkpoint_every=args.frames, log_every=500,
                           replay_capacity=max(args.frames, 1000))  # the whole live run, not 1M transitions
    live = out / "live_pretrain"
    print(f"[demo] live pre-training: dvfb on walker for {config.frames} frames (small preset) into {live}")
    pretrain(config, live, overwrite=True, progress=args.progress, command=sys.argv)
    print(f"[demo] done: {out}/ (zero-shot results in {agent_dir}/zeroshot/, the live run in {live}/)")
    return 0


def bundled_demo_run() -> Path:
    """The pre-trained DVFB walker run shipped in the package (config, snapshot, provenance)."""
    from importlib import resources

    path = Path(str(resources.files("dvfb") / "data" / "demo_walker_dvfb"))
    if not (path / "config.json").is_file():
        raise ConfigError(f"the bundled demo agent is missing from the installation ({path})")
    return path


def cmd_random_policy(args: argparse.Namespace) -> int:
    """Returns of a uniform-random policy on every task of a domain (the table's floor)."""
    from dvfb import envs
    from dvfb.runs import write_json_atomic
    from dvfb.workflows.zeroshot import random_policy_evaluation

    envs.check_domain(args.domain)
    output = Path(args.output) if args.output else None
    if output is not None and output.exists() and not args.overwrite:
        raise ConfigError(f"{output} exists; pass --overwrite to replace it")
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


def cmd_sweep(args: argparse.Namespace) -> int:
    """A grid of runs through pre-train -> zero-shot -> fine-tune -> report (dvfb.sweep)."""
    from dvfb.sweep.cli import run_from_args
    from dvfb.sweep.units import use_in_process

    use_in_process(main)  # the debug executor's phases are dvfb commands run in this process

    return run_from_args(args)


def cmd_sweep_status(args: argparse.Namespace) -> int:
    """The table of a sweep's cells: done / running / queued / failed, frames and ETA."""
    from dvfb.sweep.cli import status_from_args

    return status_from_args(args)


# ---------------------------------------------------------------------------------------------
# Reports and analyses (dvfb.analysis)


def cmd_report(args: argparse.Namespace) -> int:
    """Tables 1, 2 and 6 of the paper and fine-tuning curves from run directories."""
    from dvfb.analysis.report import make_report
    from dvfb.analysis.tables import to_markdown

    report = make_report(args.runs, args.out, spread="se" if args.stderr else "std",
                         random_files=args.random or (), overwrite=args.overwrite)
    for table in (report.zeroshot, report.finetune, report.success_zeroshot, report.success_finetune):
        if table is not None:
            print(f"## {table.title}\n\n{to_markdown(table)}\n")
    for note in report.notes:
        print(f"note: {note}")
    print(f"report written to {report.out_dir} ({len(report.files)} files; see {report.out_dir / 'report.md'})")
    return 0


def cmd_analyze_value(args: argparse.Namespace) -> int:
    """Skill value vs return (paper §4, Fig. 3b)."""
    from dvfb.analysis.value import analyze_value

    summary = analyze_value(args.run, args.task, skills=args.skills, episodes_per_skill=args.episodes_per_skill,
                            bins=args.bins, max_steps=args.max_steps, snapshot=args.snapshot, seed=args.seed,
                            inference=_protocol_overrides(args, "inference"),
                            overwrite=args.overwrite)

    def fmt(value):
        return "n/a" if value is None else f"{value:.3f}"

    print(f"{summary['trajectories']} trajectories on {args.task}: Spearman(value, return) = "
          f"{fmt(summary['spearman'])} (own-skill value: {fmt(summary['spearman_own_skill'])})")
    for b in summary["bins"]:
        print(f"  return bin {b['bin']} [{b['return_min']:.1f}, {b['return_max']:.1f}] n={b['n']}: "
              f"Spearman {fmt(b['spearman'])}")
    print("files: " + ", ".join(summary["files"]))
    return 0


def cmd_analyze_exploration(args: argparse.Namespace) -> int:
    """Skill trajectories and state coverage (paper Fig. 2)."""
    from dvfb.analysis.exploration import analyze_exploration

    summary = analyze_exploration(args.run, skills=args.skills, repeats=args.repeats, steps=args.steps,
                                  actions=args.actions, cell_size=args.cell_size, snapshot=args.snapshot,
                                  seed=args.seed, overwrite=args.overwrite)
    print(f"{summary['skills']} skills x {summary['repeats']} runs x {summary['steps']} steps "
          f"({summary['actions']} actions): coverage {summary['coverage_cells']} cells of "
          f"{summary['cell_size']:g} over ({', '.join(summary['coordinates'])}); per skill "
          f"{summary['coverage_cells_per_skill_mean']:.1f}")
    print("files: " + ", ".join(summary["files"]))
    return 0


def cmd_video(args: argparse.Namespace) -> int:
    """A video of zero-shot evaluation episodes."""
    from dvfb.analysis.video import record_video

    result = record_video(args.run, args.task, episodes=args.episodes, out=args.out, max_steps=args.max_steps,
                          frame_skip=args.frame_skip, height=args.height, width=args.width, camera=args.camera,
                          inference=_protocol_overrides(args, "inference"),
                          snapshot=args.snapshot, seed=args.seed, infer=args.infer, overwrite=args.overwrite)
    returns = ", ".join(f"{r:.1f}" for r in result["returns"])
    print(f"{result['path']}: {result['episodes']} episode(s), {result['frames']} frames at {result['fps']:g} fps; "
          f"returns {returns}; {result['skill_source']}")
    return 0


# ---------------------------------------------------------------------------------------------
# Parser


def add_snapshot_and_seed(p: argparse.ArgumentParser, seed_what: str = "seed") -> None:
    """--snapshot and --seed of the commands that load a pre-trained run's agent."""
    p.add_argument("--snapshot", type=int, default=None, help="snapshot frames (default: the latest)")
    p.add_argument("--seed", type=int, default=None, help=f"{seed_what} (default: the run's seed)")


def build_parser(agent: str = "dvfb") -> argparse.ArgumentParser:
    """The parser; ``pretrain``'s config flags are those of ``agent`` (read from ``--agent`` first)."""
    from dvfb.agents import agent_names
    from dvfb.workflows.config import PRESETS, preset_config, run_config_class

    parser = argparse.ArgumentParser(prog="dvfb", description="Online unsupervised zero-shot RL: DVFB, FB and "
                                     "baselines (`dvfb agents`).", formatter_class=_Formatter)
    parser.add_argument("--version", action="version", version=f"dvfb {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("tasks", help="print the task table", description="Print every task with its dimensions.")
    p.set_defaults(func=cmd_tasks)

    p = sub.add_parser("agents", help="list the methods", description="Every registered method with its family, "
                       "zero-shot strategy, fine-tuner and config sections.")
    p.set_defaults(func=cmd_agents)

    def progress_flag(p):
        p.add_argument("--progress", dest="progress", action="store_true", default=None,
                       help="always show the progress bar (default: only on a terminal)")
        p.add_argument("--no-progress", dest="progress", action="store_false", help="never show it")

    p = sub.add_parser(
        "pretrain", help="reward-free pre-training", formatter_class=_Formatter,
        description="Reward-free online pre-training (docs/methods.md). Defaults shown are those of the "
                    f"{DEFAULT_PRESET!r} preset for --agent {agent}; --preset paper gives the spec's values "
                    "(hidden 1024, batch 1024, 2M frames), --preset code the authors' constants. The config "
                    "sections depend on the method: `dvfb pretrain --agent NAME --help` shows its flags.")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=PRESETS, help="base configuration (default: %(default)s)")
    p.add_argument("--run-dir", default=None, help="run directory (default: runs/<agent>_<domain>_<preset>_s<seed>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its latest checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    progress_flag(p)
    p.add_argument("--agent", default=agent, choices=agent_names(), help="method (default: %(default)s)")
    add_arguments(p, run_config_class(agent), defaults=preset_config(DEFAULT_PRESET, agent), skip=("preset", "agent"))
    p.set_defaults(func=cmd_pretrain)

    p = sub.add_parser("zeroshot", help="infer z for a task and evaluate", formatter_class=_Formatter,
                       description="Zero-shot: infer z_r from reward-labelled steps (or a reward function "
                                   "or a goal) and evaluate pi(s, z_r) with mean actions (docs/methods.md §8). "
                                   "Inference defaults come from the run's config.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--task", nargs="+", required=True, help="task name(s) of the run's domain, or 'all'")
    add_snapshot_and_seed(p, "task seed")
    p.add_argument("--skill-source", "--z-source", dest="skill_source", default="rewards",
                   choices=("rewards", "reward_fn", "goal"),
                   help="where the task's skill comes from: interaction with the task (every method), a reward "
                        "function over the run's replay states, or a goal (methods that infer skills); "
                        "--z-source is the old name (default: %(default)s)")
    p.add_argument("--reward-fn", default=None, help="module:function or file.py:function mapping next_obs (N, O) to rewards")
    p.add_argument("--goal", default=None, help="goal observation: a .npy file or comma-separated numbers")
    p.add_argument("--overwrite", action="store_true", help="replace an existing result file")
    progress_flag(p)
    _add_protocol_arguments(p, "inference")
    p.set_defaults(func=cmd_zeroshot)

    p = sub.add_parser("finetune", help="fine-tune a pre-trained run on a task", formatter_class=_Formatter,
                       description="Fine-tuning by the method family's protocol: dual-value (a fresh task critic, "
                                   "reward mapping and the skill value) for DVFB/FB, URLB's (pre-trained actor, "
                                   "fresh critic with the pre-trained trunk, extrinsic n-step reward) for the "
                                   "DDPG baselines. Defaults come from the run's config.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    add_snapshot_and_seed(p)
    p.add_argument("--name", default=None, help="name of the fine-tuning run under RUN/finetune/ (default: the task)")
    p.add_argument("--resume", action="store_true", help="continue from the latest fine-tuning checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing fine-tuning run")
    progress_flag(p)
    _add_protocol_arguments(p, "inference")
    _add_protocol_arguments(p, "finetune")
    p.set_defaults(func=cmd_finetune)

    p = sub.add_parser("random-policy", help="returns of a uniform-random policy on a domain's tasks",
                       description="Evaluate a uniform-random policy on every task of a domain.")
    p.add_argument("--domain", required=True, help="domain name")
    p.add_argument("--episodes", type=int, default=10, help="episodes per task (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--output", default=None, help="write the returns to this JSON file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=cmd_random_policy)

    p = sub.add_parser("demo", help="the bundled DVFB walker zero-shot vs random, a GIF, a short live run",
                       description="The README's demo: a bundled pre-trained DVFB walker agent (made with "
                                   "`dvfb pretrain`, see its provenance.json) zero-shot on the 4 walker tasks "
                                   "against a uniform-random policy, a GIF of one task, then a short live "
                                   "pre-training on the small CPU preset.")
    p.add_argument("--out-dir", default="demo", help="(default: %(default)s; replaced on every demo)")
    p.add_argument("--frames", type=int, default=3000, help="live pre-training frames (default: %(default)s)")
    p.add_argument("--inference-steps", type=int, default=4000,
                   help="reward-labelled steps per task (default: %(default)s)")
    p.add_argument("--eval-episodes", type=int, default=2, help="evaluation episodes per task (default: %(default)s)")
    p.add_argument("--gif-task", default="walker_walk", help="task of the GIF (default: %(default)s)")
    p.add_argument("--gif-steps", type=int, default=400, help="steps in the GIF (default: %(default)s)")
    progress_flag(p)
    p.set_defaults(func=cmd_demo)

    from dvfb.sweep.cli import add_run_arguments as add_sweep_run_arguments

    p = sub.add_parser("sweep", help="methods x domains x seeds: pre-train -> zero-shot -> fine-tune -> report",
                       formatter_class=_Formatter,
                       description="Sweeps (README 'Sweeps', docs/sweeps.md): `dvfb sweep run FILE` runs a grid "
                                   "locally (default), on SLURM or in-process, resumably; `dvfb sweep status DIR` "
                                   "prints its cells.")
    sweep_sub = p.add_subparsers(dest="sweep_command", required=True, metavar="ACTION")
    q = sweep_sub.add_parser("run", help="run or continue a sweep", formatter_class=_Formatter,
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

    p = sub.add_parser(
        "report", help="Table 1 (zero-shot), Table 2 (fine-tuning), Table 6 (success rates) and fine-tuning curves",
        formatter_class=_Formatter,
        description="Markdown and CSV tables shaped like the paper's Table 1 (zero-shot) and Table 2 "
                    "(fine-tuning, last point of each curve): rows domain/task with per-domain averages, "
                    "columns methods (from the run configs: dvfb, dvfb_wo_ce, fb, ..._wo_svf, ..._wo_map), "
                    "mean ± std over seeds (ddof=1), plus expert-normalised scores (URLB expert returns, "
                    "walker and quadruped). Missing results are gaps. Fine-tuning curves are written as PNG.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories or directories containing runs")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--stderr", action="store_true", help="show the standard error over seeds instead of the std")
    p.add_argument("--random", nargs="+", action="extend", default=None, metavar="FILE.json",
                   help="random-policy files (dvfb random-policy --output) for a 'random' column; "
                        "give it after the run directories, or repeat it")
    p.add_argument("--overwrite", action="store_true", help="replace existing report files in --out")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser(
        "analyze-value", help="skill value vs return (paper §4, Fig. 3b)", formatter_class=_Formatter,
        description="Infer z_r for a task as zero-shot does, roll out mean-action episodes with z_r, prior "
                    "draws and projected interpolations between them, and report the Spearman correlation "
                    "between each trajectory's return and its skill value F(s0, a0, z_r).z_r, overall and "
                    "per return bin. Writes RUN/analysis/value_<task>.{csv,png,json}.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    p.add_argument("--skills", type=int, default=16, help="skills K, z_r included (default: %(default)s)")
    p.add_argument("--episodes-per-skill", type=int, default=2, help="episodes per skill (default: %(default)s)")
    p.add_argument("--bins", type=int, default=4, help="equal-count return bins (default: %(default)s)")
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes after this many steps (default: full)")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing analysis files")
    _add_protocol_arguments(p, "inference")
    p.set_defaults(func=cmd_analyze_value)

    p = sub.add_parser(
        "analyze-exploration", help="skill trajectories and state coverage (paper Fig. 2)",
        formatter_class=_Formatter,
        description="Run K prior skills R times each in the domain's reward-free environment, plot position "
                    "vs time (one colour per skill) and count the grid cells visited. Coordinates and "
                    "default cell sizes: walker/hopper/cheetah torso (x, z) 0.1 m, quadruped torso (x, y) "
                    "0.25 m, point_mass_maze (x, y) 0.02. Writes RUN/analysis/exploration.{png,json} and "
                    "exploration_positions.npz.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--skills", type=int, default=10, help="skills K drawn from the prior (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="runs R per skill (default: %(default)s)")
    p.add_argument("--steps", type=int, default=None,
                   help="steps per run, at most the episode length (default: one episode: 1000, Meta-World 250)")
    p.add_argument("--actions", default="rollout", choices=("rollout", "mean"),
                   help="rollout samples (sigma 0.2, as in pre-training) or mean actions (default: %(default)s)")
    p.add_argument("--cell-size", type=float, default=None, help="coverage grid cell size (default: per domain)")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing analysis files")
    p.set_defaults(func=cmd_analyze_exploration)

    p = sub.add_parser(
        "video", help="video of zero-shot evaluation episodes", formatter_class=_Formatter,
        description="Render mean-action episodes of pi(s, z_r) (z_r from RUN/zeroshot/<task>.json, else "
                    "inferred) into a GIF (no extra package) or MP4 (needs imageio-ffmpeg). Needs an OpenGL "
                    "backend: MUJOCO_GL=egl, or MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa with Debian's "
                    "libosmesa6.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    p.add_argument("--episodes", type=int, default=1, help="episodes (default: %(default)s)")
    p.add_argument("--out", default=None, help="FILE.gif or FILE.mp4 (default: RUN/analysis/video_<task>.gif)")
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes after this many steps (default: full)")
    p.add_argument("--frame-skip", type=int, default=2, help="keep every k-th frame (default: %(default)s)")
    p.add_argument("--height", type=int, default=240, help="(default: %(default)s)")
    p.add_argument("--width", type=int, default=320, help="(default: %(default)s)")
    p.add_argument("--camera", default=None, help="camera name or id (default: a per-domain view)")
    p.add_argument("--infer", action="store_true", help="infer z_r anew even if a zero-shot result exists")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing video file")
    _add_protocol_arguments(p, "inference")
    p.set_defaults(func=cmd_video)
    # Global flags are accepted after the sub-command too (`dvfb pretrain ... -v`).
    for subparser in sub.choices.values():
        subparser.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                               help="log progress messages")
    return parser


def _requested_agent(argv: list[str]) -> str:
    """The value of ``pretrain --agent`` (which decides the config flags), before the full parse."""
    from dvfb.agents import agent_names

    if "pretrain" not in argv:
        return "dvfb"
    rest = argv[argv.index("pretrain") + 1:]
    for i, token in enumerate(rest):
        value = None
        if token == "--agent" and i + 1 < len(rest):
            value = rest[i + 1]
        elif token.startswith("--agent="):
            value = token.split("=", 1)[1]
        if value is not None:
            return value if value in agent_names() else "dvfb"  # argparse names a bad choice
    return "dvfb"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_requested_agent(argv))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except RunInterrupted as exc:
        print(f"dvfb {args.command}: {exc}", file=sys.stderr)
        return 128 + exc.signum
    except DvfbError as exc:
        print(f"dvfb {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dvfb {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
