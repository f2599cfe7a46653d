"""``dvfb demo``: the README's demo with the bundled DVFB walker agent."""

from __future__ import annotations

import argparse
import json
import shutil
from importlib import resources
from pathlib import Path

import numpy as np

from dvfb import envs
from dvfb.cli.common import integer, progress_flag
from dvfb.core.errors import ConfigError, DvfbError
from dvfb.runs.directory import RunDir
from dvfb.runs.export import is_export, unpack_export
from dvfb.runs.presets import preset_config
from dvfb.workflows.pretrain import pretrain
from dvfb.workflows.video import record_video
from dvfb.workflows.zeroshot import random_policy_return, zeroshot


def cmd_demo(args: argparse.Namespace) -> int:
    """The bundled pre-trained DVFB walker zero-shot on its 4 tasks against a random policy, by its
    full protocol, as mean ± standard error with a verdict per task; a GIF of one task; then a short
    live pre-training that shows the pipeline (docs: README, "Two commands")."""
    out = Path(args.out_dir)
    # Everything the demo will need is checked before it writes anything (README, "Two commands").
    tasks = envs.tasks_of_domain("walker")
    if args.gif_task not in tasks:
        raise ConfigError(f"--gif-task {args.gif_task!r} is not a walker task (the bundled agent was pre-trained on "
                          f"walker); choose from {', '.join(tasks)}")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out-dir {out} is a file; give a directory")
    bundled = bundled_demo_run()
    agent_dir, live = out / "pretrained_dvfb_walker", out / "live_pretrain"
    for directory in (agent_dir, live):  # replaced on every demo, but only if a demo made them
        RunDir.check_new(directory, overwrite=True)
    config = preset_config("small", agent="dvfb", domain="walker", frames=args.frames, seed=0,
                           seed_frames=min(1000, args.frames // 2), checkpoint_every=args.frames, log_every=500,
                           replay_capacity=max(args.frames, 1000))  # the whole live run, not 1M transitions
    provenance = json.loads((bundled / "provenance.json").read_text())
    if agent_dir.exists():
        shutil.rmtree(agent_dir)
    # The agent ships as an exported model (docs/sharing.md); the commands below take a run
    # directory, so it is unpacked into one: its config and its one snapshot.
    unpack_export(bundled, agent_dir, command=args.command_line)
    shutil.copy(bundled / "provenance.json", agent_dir / "provenance.json")
    print(f"[demo] bundled agent: {provenance['what']}; {provenance['frames']:,} pre-training frames, "
          f"{provenance['preset']} preset (how it was made: {agent_dir / 'provenance.json'})")
    # The agent's own zero-shot protocol (the one `dvfb zeroshot` runs), with the demo's episodes.
    inference = {"eval_episodes": args.eval_episodes}
    if args.inference_steps is not None:
        inference.update(steps=args.inference_steps, samples=args.inference_steps,
                         random_action_steps=args.inference_steps * 2 // 5)
    steps = args.inference_steps or zeroshot_protocol_steps(agent_dir)
    print(f"[demo] zero-shot: z_r inferred from {steps:,} reward-labelled steps per task, then "
          f"{args.eval_episodes} evaluation episodes; random policy: {args.eval_episodes} episodes; "
          "mean ± standard error over the episodes")
    rows = []
    for task in tasks:
        result = zeroshot(agent_dir, task, inference=inference, overwrite=True, progress=args.progress)
        random_returns = random_policy_return(task, args.eval_episodes, seed=0)
        rows.append((task, result["returns"], random_returns))
    print(demo_table(rows))
    gif = out / f"{args.gif_task}.gif"
    try:
        video = record_video(agent_dir, args.gif_task, out=gif, max_steps=args.gif_steps, frame_skip=4,
                             height=160, width=200, overwrite=True)
        print(f"[demo] {video['path']}: zero-shot {args.gif_task}, {video['frames']} frames")
    except (DvfbError, RuntimeError) as exc:  # rendering needs OpenGL; the rest of the demo does not
        print(f"[demo] no GIF: {exc}")
    print(f"[demo] live pre-training: dvfb on walker for {config.frames} frames (small preset) into {live}")
    pretrain(config, live, overwrite=True, progress=args.progress, command=args.command_line)
    print(f"[demo] done: {out}/ (zero-shot results in {agent_dir}/zeroshot/, the live run in {live}/)")
    return 0


def mean_and_error(returns) -> tuple[float, float]:
    """The mean of episode returns and its standard error (std with ddof = 1 over sqrt(n); 0 for one)."""
    values = np.asarray(returns, dtype=float)
    error = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0
    return float(values.mean()), error


def verdict(agent_returns, random_returns) -> str:
    """How DVFB compares with the random policy on a task: apart only when the means differ by more
    than two standard errors of their difference; otherwise the demo does not rank them (a
    machine's floating-point rounding can flip such a ranking)."""
    (a, ea), (r, er) = mean_and_error(agent_returns), mean_and_error(random_returns)
    if abs(a - r) <= 2.0 * float(np.hypot(ea, er)):
        return "not distinguishable"
    return "DVFB above random" if a > r else "DVFB below random"


def demo_table(rows) -> str:
    """The demo's table: per task, DVFB and the random policy as mean ± standard error, and the verdict."""
    header = f"{'task':<14} {'DVFB zero-shot':>16} {'random policy':>16}  {'(2 standard errors apart?)'}"
    lines = [header, "-" * len(header)]
    for task, agent_returns, random_returns in rows:
        (a, ea), (r, er) = mean_and_error(agent_returns), mean_and_error(random_returns)
        lines.append(f"{task:<14} {f'{a:.1f} ± {ea:.1f}':>16} {f'{r:.1f} ± {er:.1f}':>16}  "
                     f"{verdict(agent_returns, random_returns)}")
    return "\n".join(lines)


def zeroshot_protocol_steps(run_dir: Path) -> int:
    """The reward-labelled steps of the run's own zero-shot protocol (its config's inference section)."""
    config = json.loads((run_dir / "config.json").read_text())
    return int(config["inference"]["steps"])


def bundled_demo_run() -> Path:
    """The pre-trained DVFB walker agent shipped in the package: an exported model (safetensors,
    config.json, model card; docs/sharing.md) and its provenance.json."""
    path = Path(str(resources.files("dvfb") / "data" / "demo_walker_dvfb"))
    if not is_export(path):
        raise ConfigError(f"the bundled demo agent is missing from the installation ({path})")
    return path


def register(sub, agent: str) -> None:
    p = sub.add_parser("demo", help="the bundled DVFB walker zero-shot vs random, a GIF, a short live run",
                       description="The README's demo: a bundled pre-trained DVFB walker agent (made with "
                                   "`dvfb pretrain`, see its provenance.json) zero-shot on the 4 walker tasks "
                                   "against a uniform-random policy, a GIF of one task, then a short live "
                                   "pre-training on the small CPU preset.")
    p.add_argument("--out-dir", default="demo", help="(default: %(default)s; replaced on every demo)")
    p.add_argument("--frames", type=integer(1), default=3000, help="live pre-training frames (default: %(default)s)")
    p.add_argument("--inference-steps", type=integer(1), default=None,
                   help="reward-labelled steps per task (default: the agent's own protocol, 10,000 at the small "
                        "preset, 40%% of them with uniform actions)")
    p.add_argument("--eval-episodes", type=integer(2), default=10,
                   help="evaluation episodes per task, for DVFB and the random policy (default: %(default)s)")
    p.add_argument("--gif-task", default="walker_walk", help="task of the GIF (default: %(default)s)")
    p.add_argument("--gif-steps", type=integer(1), default=400, help="steps in the GIF (default: %(default)s)")
    progress_flag(p)
    p.set_defaults(func=cmd_demo)
