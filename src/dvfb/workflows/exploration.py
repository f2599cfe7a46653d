"""Exploration analysis (paper Fig. 2): where do the pre-trained skills go, and how much do they cover?

``dvfb analyze-exploration RUN`` draws K skills ``z ~ p(z)`` (docs/methods.md §5.1) from the
pre-trained model, runs each R times for S steps (default: one episode) in the domain's reward-free
pre-training environment, and records physical positions at every step:

===================  ==========================================  ===========  ==================
domain               recorded coordinates                        plotted      default cell size
===================  ==========================================  ===========  ==================
walker, hopper,      torso x, torso z (``data.xpos['torso']``)   x over time  0.1 m
cheetah
quadruped            torso x, torso y (``data.xpos['torso']``)   x, y; path   0.25 m
point_mass_maze      root_x, root_y (``data.qpos``)              x, y; path   0.02 (a 30 x 30
                                                                              grid over the maze)
metaworld            hand x, hand y (``data.body('hand').xpos``)  x, y; path   0.02 m
===================  ==========================================  ===========  ==================

Actions are **rollout samples** of ``pi(s, z)`` (sigma 0.2, §3.3) by default -- the behaviour that
collected the pre-training data -- or the mean action with ``actions="mean"``.

State coverage (the number to compare methods by) is the number of distinct grid cells
``floor(coordinate / cell_size)`` (per recorded coordinate, grid anchored at 0) occupied by any
recorded state of any skill. The per-skill coverage (cells of one skill's R runs) is also reported.

Outputs under ``RUN/analysis/``: ``exploration.png`` (position vs time, one colour per skill; for
2-D domains also the path in the plane), ``exploration.json`` (settings and coverage) and
``exploration_positions.npz`` (the positions, shape (K, R, S + 1, C)).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dvfb import envs
from dvfb.analysis.common import AnalysisError, json_safe
from dvfb.analysis.statistics import coverage
from dvfb.runs import check_writable, write_json_atomic
from dvfb.runs.snapshots import load_model
from dvfb.training.evaluation import run_episode
from dvfb.training.observers import ProgressCount
from dvfb.training.progress import Progress
from dvfb.training.rollout import Observer
from dvfb.training.seeding import run_generator, seed_everything
from dvfb.workflows.resources import open_run

ACTION_MODES = ("rollout", "mean")


@dataclass(frozen=True)
class Coordinates:
    names: tuple[str, ...]
    read: Callable[[object], tuple[float, ...]]  # the (unwrapped) env -> one value per name
    cell_size: float
    planar: bool  # True: the first two coordinates are a horizontal plane (x, y)


def _torso_xz(env) -> tuple[float, float]:
    x, _, z = env.physics.named.data.xpos["torso"]
    return float(x), float(z)


def _torso_xy(env) -> tuple[float, float]:
    x, y, _ = env.physics.named.data.xpos["torso"]
    return float(x), float(y)


def _maze_xy(env) -> tuple[float, float]:
    qpos = env.physics.named.data.qpos
    return float(qpos["root_x"][0]), float(qpos["root_y"][0])


def _hand_xy(env) -> tuple[float, float]:
    x, y, _ = env.mw_env.data.body("hand").xpos
    return float(x), float(y)


COORDINATES: dict[str, Coordinates] = {
    "walker": Coordinates(("torso_x", "torso_z"), _torso_xz, 0.1, False),
    "hopper": Coordinates(("torso_x", "torso_z"), _torso_xz, 0.1, False),
    "cheetah": Coordinates(("torso_x", "torso_z"), _torso_xz, 0.1, False),
    "quadruped": Coordinates(("torso_x", "torso_y"), _torso_xy, 0.25, True),
    "point_mass_maze": Coordinates(("x", "y"), _maze_xy, 0.02, True),
    "metaworld": Coordinates(("hand_x", "hand_y"), _hand_xy, 0.02, True),
}


class Positions(Observer):
    """The recorded coordinates of every state of an episode: row 0 at the reset, row t + 1 after
    step t."""

    def __init__(self, rows: np.ndarray, coords: Coordinates, env):
        self.rows, self.coords, self.env = rows, coords, env

    def episode_started(self, lane: int, obs) -> None:
        self.rows[0] = self.coords.read(self.env)

    def transition(self, lane: int, step: int, action, reward, discount, next_obs, info) -> None:
        self.rows[step + 1] = self.coords.read(self.env)


def analyze_exploration(run_path: str | Path, *, skills: int = 10, repeats: int = 3, steps: int | None = None,
                        actions: str = "rollout", cell_size: float | None = None, snapshot: int | None = None,
                        seed: int | None = None, overwrite: bool = False, device: str | None = None,
                        progress: bool | None = None, torch_threads: int | None = None) -> dict:
    """Run the analysis of the module docstring on a pre-trained run; returns the JSON summary.
    ``progress`` as :class:`~dvfb.training.progress.Progress` takes it; ``torch_threads``: the
    command's (:func:`~dvfb.workflows.resources.use_threads`)."""

    if actions not in ACTION_MODES:
        raise AnalysisError(f"--actions must be one of {', '.join(ACTION_MODES)}, got {actions!r}")
    for name, value in (("--skills", skills), ("--repeats", repeats), ("--steps", 1 if steps is None else steps)):
        if value < 1:
            raise AnalysisError(f"{name} must be at least 1")
    run = open_run(run_path, torch_threads)
    config = run.config
    episode_length = envs.TASKS[envs.pretrain_task(config.domain)].episode_length
    steps = episode_length if steps is None else steps  # by default a whole episode
    if steps > episode_length:
        raise AnalysisError(f"--steps must be at most the episode length ({episode_length})")
    if config.domain not in COORDINATES:
        raise AnalysisError(f"no position coordinates are defined for domain {config.domain!r}")
    coords = COORDINATES[config.domain]
    cell = coords.cell_size if cell_size is None else float(cell_size)
    if not cell > 0 or cell == float("inf"):  # also NaN
        raise AnalysisError(f"--cell-size must be a positive finite number, got {cell!r}")
    out_dir = run.analysis_dir
    outputs = [out_dir / "exploration.png", out_dir / "exploration.json", out_dir / "exploration_positions.npz"]
    existing = [p for p in outputs if p.exists()]
    if existing and not overwrite:
        raise AnalysisError(f"{existing[0]} exists; pass --overwrite to replace it")
    model, snapshot = load_model(run, snapshot, device)
    seed = config.seed if seed is None else seed
    seed_everything(seed)
    model.use_generator(run_generator(seed, model.device))  # the analysis' own random stream
    started = time.time()
    zs = model.sample_skill(skills)
    if zs is None:
        raise AnalysisError(f"analyze-exploration compares skills; {config.agent!r} has a single policy")
    check_writable(out_dir)  # a read-only run fails now, not after the rollouts
    env = envs.make(config.domain, seed=seed, reward_free=True)
    source = env.unwrapped
    positions = np.full((skills, repeats, steps + 1, len(coords.names)), np.nan)
    bar = Progress(skills * repeats * steps, 0, "analyze-exploration", progress, unit="step")
    try:
        for k in range(skills):
            for r in range(repeats):
                # An episode's end stops its record (never before ``steps`` in DMC; the rest would stay NaN).
                run_episode(env, model.act, zs[k], actions == "rollout",
                            [Positions(positions[k, r], coords, source), ProgressCount(bar)], max_steps=steps)
    finally:
        bar.close()
    recorded = positions[~np.isnan(positions).any(-1)]
    per_skill = [coverage(positions[k][~np.isnan(positions[k]).any(-1)], cell) for k in range(skills)]
    x = positions[..., 0]
    summary = {
        "analysis": "skill exploration and state coverage (paper Fig. 2)", "run": str(run.path),
        "agent": config.agent, "domain": config.domain, "snapshot_frames": snapshot, "seed": seed,
        "skills": skills, "repeats": repeats, "steps": steps, "actions": actions,
        "coordinates": list(coords.names), "cell_size": cell,
        "coverage_cells": coverage(recorded, cell), "coverage_cells_per_skill_mean": float(np.mean(per_skill)),
        "coverage_cells_per_skill": per_skill,
        "x_displacement_mean": float(np.nanmean(np.abs(x[:, :, -1] - x[:, :, 0]))),
        "x_range": [float(np.nanmin(x)), float(np.nanmax(x))],
        "wall_clock_s": time.time() - started, "files": [str(p) for p in outputs],
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(outputs[2], positions=positions, z=zs.cpu().numpy(), coordinates=np.array(coords.names))
    _plot(outputs[0], positions, coords, envs.TASKS[envs.pretrain_task(config.domain)].control_dt, summary)
    summary = json_safe(summary)
    write_json_atomic(outputs[1], summary)
    return summary


def _draw_maze(ax) -> None:
    """The maze's arena (+-0.3) and its plus-shaped interior walls (docs/tasks.md §6), to scale."""
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((-0.3, -0.3), 0.6, 0.6, fill=False, edgecolor="0.3", lw=1))
    ax.add_patch(Rectangle((-0.18, -0.02), 0.36, 0.04, color="0.6", alpha=0.6, lw=0))
    ax.add_patch(Rectangle((-0.02, -0.18), 0.04, 0.36, color="0.6", alpha=0.6, lw=0))
    ax.set_xlim(-0.32, 0.32)
    ax.set_ylim(-0.32, 0.32)


def _plot(path: Path, positions: np.ndarray, coords: Coordinates, dt: float, summary: dict) -> None:
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    skills, repeats, length, _ = positions.shape
    time_axis = np.arange(length) * dt
    panels = 3 if coords.planar else 1
    fig = Figure(figsize=(4.6 * panels, 3.8), dpi=100, layout="constrained")
    axes = [fig.add_subplot(1, panels, i + 1) for i in range(panels)]
    cmap = colormaps["tab10" if skills <= 10 else "viridis"]
    colour = (lambda k: cmap(k % 10)) if skills <= 10 else (lambda k: cmap(k / max(skills - 1, 1)))
    for k in range(skills):
        for r in range(repeats):
            label = f"skill {k}" if r == 0 and skills <= 10 else None
            axes[0].plot(time_axis, positions[k, r, :, 0], color=colour(k), lw=1, alpha=0.8, label=label)
            if coords.planar:
                axes[1].plot(time_axis, positions[k, r, :, 1], color=colour(k), lw=1, alpha=0.8)
                axes[2].plot(positions[k, r, :, 0], positions[k, r, :, 1], color=colour(k), lw=1, alpha=0.8)
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel(f"{coords.names[0]}")
    if coords.planar:
        axes[1].set_xlabel("time (s)")
        axes[1].set_ylabel(coords.names[1])
        axes[2].set_xlabel(coords.names[0])
        axes[2].set_ylabel(coords.names[1])
        axes[2].set_aspect("equal", adjustable="datalim")
        axes[2].set_title("path in the plane")
        if summary["domain"] == "point_mass_maze":
            _draw_maze(axes[2])
    for ax in axes:
        ax.grid(alpha=0.3)
    if skills <= 10:
        axes[0].legend(fontsize=7, ncol=2)
    # Two short lines: one long line is wider than a single-panel figure and gets clipped.
    fig.suptitle(f"{summary['agent']} on {summary['domain']}: {skills} skills x {repeats} runs "
                 f"({summary['actions']} actions)\ncoverage {summary['coverage_cells']} cells of "
                 f"{summary['cell_size']:g}", fontsize=10)
    fig.savefig(path)
