"""``dvfb video``: a video of zero-shot evaluation episodes."""

from __future__ import annotations

import argparse

from dvfb.cli.common import (Formatter, add_protocol_arguments, add_snapshot_and_seed, eval_dir_flag, evaluated,
                             integer, progress_flag, protocol_overrides, torch_threads_flag)
from dvfb.workflows.video import record_video


def cmd_video(args: argparse.Namespace) -> int:
    """A video of zero-shot evaluation episodes, of a run or an exported model (docs/sharing.md, "Evaluate")."""
    with evaluated(args.run, args.eval_dir, args.command_line) as ([run], _data, _exported):
        result = record_video(run, args.task, episodes=args.episodes, out=args.out, max_steps=args.max_steps,
                              frame_skip=args.frame_skip, height=args.height, width=args.width, camera=args.camera,
                              inference=protocol_overrides(args, "inference"), snapshot=args.snapshot,
                              seed=args.seed, infer=args.infer, overwrite=args.overwrite, progress=args.progress,
                              torch_threads=args.torch_threads)
    returns = ", ".join(f"{r:.1f}" for r in result["returns"])
    print(f"{result['path']}: {result['episodes']} episode(s), {result['frames']} frames at {result['fps']:g} fps; "
          f"returns {returns}; {result['skill_source']}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "video", help="video of zero-shot evaluation episodes", formatter_class=Formatter,
        description="Render mean-action episodes of pi(s, z_r) (z_r from RUN/zeroshot/<task>.json, else "
                    "inferred) into a GIF (no extra package) or MP4 (needs imageio-ffmpeg). Needs an OpenGL "
                    "backend: MUJOCO_GL=egl, or MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa with Debian's "
                    "libosmesa6. An exported model is rendered from its evaluation directory (EXPORT.eval, or "
                    "--eval-dir: where `dvfb zeroshot EXPORT` put its results; docs/sharing.md, \"Evaluate\").")
    p.add_argument("run", help="pre-training run directory, or an exported model's directory")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    p.add_argument("--episodes", type=integer(1), default=1, help="episodes (default: %(default)s)")
    p.add_argument("--out", default=None, help="FILE.gif or FILE.mp4 (default: RUN/analysis/video_<task>.gif)")
    p.add_argument("--max-steps", type=integer(1), default=None, help="cut episodes after this many steps (default: full)")
    p.add_argument("--frame-skip", type=integer(1), default=2, help="keep every k-th frame (default: %(default)s)")
    p.add_argument("--height", type=integer(1), default=240, help="(default: %(default)s)")
    p.add_argument("--width", type=integer(1), default=320, help="(default: %(default)s)")
    p.add_argument("--camera", default=None, help="camera name or id (default: a per-domain view)")
    p.add_argument("--infer", action="store_true", help="infer z_r anew even if a zero-shot result exists")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing video file")
    eval_dir_flag(p)
    progress_flag(p)
    torch_threads_flag(p)
    add_protocol_arguments(p, "inference")
    p.set_defaults(func=cmd_video)
