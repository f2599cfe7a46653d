"""``dvfb demo``: the README's demo with the bundled DVFB walker agent."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dvfb.cli.common import integer, progress_flag
from dvfb.errors import ConfigError

def cmd_demo(args: argparse.Namespace) -> int:
    """The bundled pre-trained DVFB walker zero-shot on its 4 tasks against a random policy, a GIF of
    one task, then a short live pre-training that shows the pipeline (docs: README, "Two commands")."""
    import shutil

    # lazy: the command's machinery loads when it runs (a fast `dvfb --help`)
    from dvfb import envs
    from dvfb.workflows.video import record_video
    from dvfb.errors import DvfbError
    from dvfb.runs.export import unpack_export
    from dvfb.runs.presets import preset_config
    from dvfb.workflows.pretrain import pretrain
    from dvfb.workflows.zeroshot import random_policy_return, zeroshot

    out = Path(args.out_dir)
    bundled = bundled_demo_run()
    agent_dir = out / "pretrained_dvfb_walker"
    provenance = json.loads((bundled / "provenance.json").read_text())
    if agent_dir.exists():
        shutil.rmtree(agent_dir)
    # The agent ships as an exported model (docs/sharing.md); the commands below take a run
    # directory, so it is unpacked into one: its config and its one snapshot.
    unpack_export(bundled, agent_dir, command=args.command_line)
    shutil.copy(bundled / "provenance.json", agent_dir / "provenance.json")
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
    pretrain(config, live, overwrite=True, progress=args.progress, command=args.command_line)
    print(f"[demo] done: {out}/ (zero-shot results in {agent_dir}/zeroshot/, the live run in {live}/)")
    return 0


def bundled_demo_run() -> Path:
    """The pre-trained DVFB walker agent shipped in the package: an exported model (safetensors,
    config.json, model card; docs/sharing.md) and its provenance.json."""
    from importlib import resources

    # lazy: the command's machinery loads when it runs (a fast `dvfb --help`)
    from dvfb.runs.export import is_export

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
    p.add_argument("--inference-steps", type=integer(1), default=4000,
                   help="reward-labelled steps per task (default: %(default)s)")
    p.add_argument("--eval-episodes", type=integer(1), default=2, help="evaluation episodes per task (default: %(default)s)")
    p.add_argument("--gif-task", default="walker_walk", help="task of the GIF (default: %(default)s)")
    p.add_argument("--gif-steps", type=integer(1), default=400, help="steps in the GIF (default: %(default)s)")
    progress_flag(p)
    p.set_defaults(func=cmd_demo)
