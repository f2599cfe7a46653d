"""Videos of zero-shot evaluation episodes (``dvfb video``), rendered headless through MuJoCo.

The policy is the zero-shot evaluation policy of docs/methods.md §8.3: mean actions of
``pi(s, z_r)``. z_r is read from ``RUN/zeroshot/<task>.json`` when that result exists for the same
snapshot (so the video shows the policy that was scored), otherwise it is inferred as zero-shot
does (§8.1-8.2, budgets from ``--inference.*``).

Rendering needs an OpenGL backend, chosen by the ``MUJOCO_GL`` environment variable before
dm_control is imported (``dvfb.envs`` picks ``egl`` on a headless machine with an EGL library, see
``dvfb/envs/_mujoco_gl.py``). When no backend works, :class:`RenderError` (exit status 2 in the
CLI) says how to enable one: ``MUJOCO_GL=egl``, or ``MUJOCO_GL=osmesa`` with
``PYOPENGL_PLATFORM=osmesa`` and Debian's ``libosmesa6`` package.

Formats, chosen by the file suffix: ``.gif`` through imageio's Pillow plugin (no extra package);
``.mp4`` through imageio's ffmpeg plugin, which needs the ``imageio-ffmpeg`` package (a PyPI wheel
that bundles an ffmpeg binary: ``pip install imageio-ffmpeg``).
"""

from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path

import imageio.v2 as iio2
import imageio.v3 as iio3
import numpy as np
import torch

from dvfb import envs
from dvfb.analysis.common import AnalysisError
from dvfb.core.errors import DvfbError
from dvfb.runs import check_writable
from dvfb.runs.snapshots import load_model
from dvfb.training.evaluation import run_episode
from dvfb.training.observers import ProgressCount
from dvfb.training.progress import Progress
from dvfb.training.rollout import Observer
from dvfb.training.seeding import run_generator, seed_everything
from dvfb.workflows.resources import check_task_in_domain, open_run
from dvfb.workflows.zeroshot import run_protocol

FORMATS = (".gif", ".mp4")
# Camera per domain: the tracking side views of the stock models, the maze's top-down view, and
# the authors' corner view for Meta-World (docs/tasks.md §4.6).
DEFAULT_CAMERAS = {"walker": "side", "hopper": "cam0", "cheetah": "side", "quadruped": "y",
                   "point_mass_maze": "fixed", "metaworld": "corner2"}


class RenderError(AnalysisError):
    """No OpenGL backend works (or the chosen one failed): says how to enable one."""


def gl_hint() -> str:
    """How to get a working MuJoCo OpenGL backend on a headless machine."""
    return ("MuJoCo needs an OpenGL backend to render: set MUJOCO_GL=egl (GPU driver or Mesa's EGL) or "
            "MUJOCO_GL=osmesa with PYOPENGL_PLATFORM=osmesa (software rendering; on Debian/Ubuntu install it "
            "with `apt-get install libosmesa6`) before running dvfb, e.g. "
            "`MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa dvfb video RUN --task TASK`")


def _render_error(exc: BaseException) -> RenderError:
    backend = os.environ.get("MUJOCO_GL")
    backend = f"MUJOCO_GL={backend}" if backend else "MUJOCO_GL unset"
    detail = (str(exc).strip().splitlines() or [""])[0]
    return RenderError(f"cannot render ({backend}; {type(exc).__name__}: {detail}). {gl_hint()}")


def check_output(path: Path) -> None:
    """The suffix must be a supported format; MP4 needs imageio-ffmpeg."""
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise AnalysisError(f"unsupported video format {path.suffix or '(no suffix)'!r} for {path}; "
                            f"use one of {', '.join(FORMATS)}")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise AnalysisError("writing MP4 needs the imageio-ffmpeg package (`pip install imageio-ffmpeg`, a "
                            "wheel that bundles ffmpeg); or write a GIF instead: --out FILE.gif")


class Renderer:
    """Frames of one environment (a dm_control task's physics, or an env with its own
    ``render_frame``: Meta-World); failures become :class:`RenderError`."""

    def __init__(self, env, height: int, width: int, camera: str | int):
        unwrapped = env.unwrapped
        self.physics = getattr(unwrapped, "physics", None)
        self.env = None if self.physics is not None else unwrapped
        self.height, self.width = height, width
        if isinstance(camera, str) and not camera.lstrip("-").isdigit():
            if self.physics is not None:
                model = self.physics.model
                names = [model.id2name(i, "camera") for i in range(model.ncam)]
            else:
                names = unwrapped.camera_names
            if camera not in names:
                raise AnalysisError(f"unknown camera {camera!r}; this model has {', '.join(names) or 'none'} "
                                    "(or give a camera id, -1 = free camera)")
            self.camera = names.index(camera)
        else:
            self.camera = int(camera)

    def frame(self) -> np.ndarray:
        try:
            if self.env is not None:
                return self.env.render_frame(self.height, self.width, self.camera)
            return self.physics.render(height=self.height, width=self.width, camera_id=self.camera)
        except DvfbError:
            raise
        except Exception as exc:  # noqa: BLE001 - every backend fails differently (RuntimeError, ImportError, EGL errors)
            raise _render_error(exc) from exc

    def close(self) -> None:
        # Freeing the GL context now avoids dm_control's noisy clean-up at interpreter exit.
        try:
            if self.env is not None:
                self.env.close()
            else:
                self.physics.free()
        except Exception:  # noqa: BLE001
            pass


class Frames(Observer):
    """The frames of an episode: one at the reset, then one every ``frame_skip`` steps."""

    def __init__(self, frames: list, renderer: Renderer, frame_skip: int):
        self.frames, self.renderer, self.frame_skip = frames, renderer, frame_skip

    def episode_started(self, lane: int, obs) -> None:
        self.frames.append(self.renderer.frame())

    def transition(self, lane: int, step: int, action, reward, discount, next_obs, info) -> None:
        if (step + 1) % self.frame_skip == 0:
            self.frames.append(self.renderer.frame())


def make_render_env(task: str, seed: int):
    """The task's environment; dm_control's import fails here when MUJOCO_GL is invalid."""

    try:
        return envs.make(task, seed=seed)
    except DvfbError:
        raise
    except (RuntimeError, ImportError, OSError) as exc:
        raise _render_error(exc) from exc


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """GIF (Pillow, frame duration in ms, looping) or MP4 (ffmpeg, H.264)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        # GIF frame delays are whole centiseconds (Pillow truncates milliseconds to them), and viewers
        # replace delays under 20 ms by 100 ms: round to the nearest 10 ms, at least 20 ms.
        delay_ms = 10 * max(2, round(100.0 / fps))
        iio3.imwrite(path, np.stack(frames), extension=".gif", duration=delay_ms, loop=0)
    else:
        with iio2.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7,
                             macro_block_size=8) as writer:
            for frame in frames:
                writer.append_data(frame)


def _stored_vector(run, model, task: str, snapshot: int, infer: bool) -> tuple[torch.Tensor, str] | None:
    """z_r of the run's zero-shot result of ``task`` for this snapshot; None when there is none (or
    ``infer`` asks for a new one)."""
    stored = run.zeroshot_result(task, snapshot)
    result = None if infer else run.read_zeroshot_result(task, snapshot, AnalysisError)
    if result is not None and isinstance(result.z, list) and result.snapshot_frames == snapshot:
        return torch.tensor(result.z, dtype=torch.float32, device=model.device), f"z from {stored}"
    return None


def _inferred_vector(config, model, task: str, inference: dict | None, seed: int, progress) -> tuple[torch.Tensor, str]:
    protocol = run_protocol(config, inference)
    rng = seed_everything(seed)
    model.use_generator(run_generator(seed, model.device))  # the analysis' own random stream
    env = envs.make(task, seed=seed)
    z, _info = protocol.task_skill(model, env, rng, envs.TASKS[task].episode_length, progress=progress)
    return z, f"skill found by {protocol.name} in {protocol.task_steps()} reward-labelled steps"


def record_video(run_path: str | Path, task: str, *, episodes: int = 1, out: str | Path | None = None,
                 max_steps: int | None = None, frame_skip: int = 2, height: int = 240, width: int = 320,
                 camera: str | int | None = None, inference: dict | None = None, snapshot: int | None = None,
                 seed: int | None = None, infer: bool = False, overwrite: bool = False,
                 device: str | None = None, progress: bool | None = None, torch_threads: int | None = None) -> dict:
    """Render ``episodes`` evaluation episodes of the run's zero-shot policy on ``task`` into one video.
    ``progress`` as :class:`~dvfb.training.progress.Progress` takes it; ``torch_threads``: the
    command's (:func:`~dvfb.workflows.resources.use_threads`)."""

    for name, value in (("--episodes", episodes), ("--frame-skip", frame_skip), ("--height", height),
                        ("--width", width)):
        if value < 1:
            raise AnalysisError(f"{name} must be at least 1")
    if max_steps is not None and max_steps < 1:
        raise AnalysisError("--max-steps must be at least 1")
    run = open_run(run_path, torch_threads)
    config = run.config
    check_task_in_domain(task, config.domain)
    out = Path(out) if out is not None else run.analysis_dir / f"video_{task}.gif"
    check_output(out)
    if out.exists() and not overwrite:
        raise AnalysisError(f"{out} exists; pass --overwrite to replace it")
    check_writable(out.parent)  # a read-only or full disk fails now, not after the episodes
    seed = config.seed if seed is None else seed
    started = time.time()

    # Rendering is checked first, so a missing backend fails in seconds, before any inference.
    env = make_render_env(task, seed)
    renderer = Renderer(env, height, width, DEFAULT_CAMERAS.get(config.domain, 0) if camera is None else camera)
    try:
        env.reset()
        renderer.frame()
        model, snapshot = load_model(run, snapshot, device)
        stored = _stored_vector(run, model, task, snapshot, infer)
        length = envs.TASKS[task].episode_length
        steps = episodes * (length if max_steps is None else min(max_steps, length))
        if stored is None:
            steps += run_protocol(config, inference).task_steps()
        # Rendering is slow (software OpenGL): the steps counted, so that a long video shows progress.
        bar = Progress(steps, 0, f"video {task}", progress, unit="step")
        try:
            z, skill_source = stored or _inferred_vector(config, model, task, inference, seed, bar)
            frames, returns = [], []
            fps = env.metadata["render_fps"] / frame_skip
            for episode in range(episodes):
                # Reseeding gives the first episode the initial state of the zero-shot evaluation's first.
                lane = run_episode(env, model.act, z, False, [Frames(frames, renderer, frame_skip), ProgressCount(bar)],
                                   max_steps, reset_seed=seed if episode == 0 else None)
                returns.append(lane.state.episode_return)
        finally:
            bar.close()
    finally:
        renderer.close()
    write_video(out, frames, fps)
    return {"path": str(out), "task": task, "episodes": episodes, "returns": returns, "frames": len(frames),
            "fps": fps, "skill_source": skill_source, "snapshot_frames": snapshot, "wall_clock_s": time.time() - started}
