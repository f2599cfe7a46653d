"""``dvfb analyze-value`` and ``dvfb analyze-exploration``: the paper's analyses of a run."""

from __future__ import annotations

import argparse

from dvfb.cli.common import (Formatter, add_protocol_arguments, add_snapshot_and_seed, integer, progress_flag,
                             protocol_overrides, torch_threads_flag)
from dvfb.workflows.exploration import analyze_exploration
from dvfb.workflows.value import analyze_value


def cmd_analyze_value(args: argparse.Namespace) -> int:
    """Skill value vs return (paper §4, Fig. 3b)."""
    summary = analyze_value(args.run, args.task, skills=args.skills, episodes_per_skill=args.episodes_per_skill,
                            bins=args.bins, max_steps=args.max_steps, snapshot=args.snapshot, seed=args.seed,
                            inference=protocol_overrides(args, "inference"),
                            overwrite=args.overwrite, torch_threads=args.torch_threads)

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
    summary = analyze_exploration(args.run, skills=args.skills, repeats=args.repeats, steps=args.steps,
                                  actions=args.actions, cell_size=args.cell_size, snapshot=args.snapshot,
                                  seed=args.seed, overwrite=args.overwrite, progress=args.progress,
                                  torch_threads=args.torch_threads)
    print(f"{summary['skills']} skills x {summary['repeats']} runs x {summary['steps']} steps "
          f"({summary['actions']} actions): coverage {summary['coverage_cells']} cells of "
          f"{summary['cell_size']:g} over ({', '.join(summary['coordinates'])}); per skill "
          f"{summary['coverage_cells_per_skill_mean']:.1f}")
    print("files: " + ", ".join(summary["files"]))
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "analyze-value", help="skill value vs return (paper §4, Fig. 3b)", formatter_class=Formatter,
        description="Infer z_r for a task as zero-shot does, roll out mean-action episodes with z_r, prior "
                    "draws and projected interpolations between them, and report the Spearman correlation "
                    "between each trajectory's return and its skill value F(s0, a0, z_r).z_r, overall and "
                    "per return bin. Writes RUN/analysis/value_<task>.{csv,png,json}.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--task", required=True, help="task name of the run's domain")
    p.add_argument("--skills", type=integer(1), default=16, help="skills K, z_r included (default: %(default)s)")
    p.add_argument("--episodes-per-skill", type=integer(1), default=2, help="episodes per skill (default: %(default)s)")
    p.add_argument("--bins", type=integer(1), default=4, help="equal-count return bins (default: %(default)s)")
    p.add_argument("--max-steps", type=integer(1), default=None, help="cut episodes after this many steps (default: full)")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing analysis files")
    torch_threads_flag(p)
    add_protocol_arguments(p, "inference")
    p.set_defaults(func=cmd_analyze_value)

    p = sub.add_parser(
        "analyze-exploration", help="skill trajectories and state coverage (paper Fig. 2)",
        formatter_class=Formatter,
        description="Run K prior skills R times each in the domain's reward-free environment, plot position "
                    "vs time (one colour per skill) and count the grid cells visited. Coordinates and "
                    "default cell sizes: walker/hopper/cheetah torso (x, z) 0.1 m, quadruped torso (x, y) "
                    "0.25 m, point_mass_maze (x, y) 0.02. Writes RUN/analysis/exploration.{png,json} and "
                    "exploration_positions.npz.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--skills", type=integer(1), default=10, help="skills K drawn from the prior (default: %(default)s)")
    p.add_argument("--repeats", type=integer(1), default=3, help="runs R per skill (default: %(default)s)")
    p.add_argument("--steps", type=integer(1), default=None,
                   help="steps per run, at most the episode length (default: one episode: 1000, Meta-World 250)")
    p.add_argument("--actions", default="rollout", choices=("rollout", "mean"),
                   help="rollout samples (sigma 0.2, as in pre-training) or mean actions (default: %(default)s)")
    p.add_argument("--cell-size", type=float, default=None, help="coverage grid cell size (default: per domain)")
    add_snapshot_and_seed(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing analysis files")
    progress_flag(p)
    torch_threads_flag(p)
    p.set_defaults(func=cmd_analyze_exploration)
