"""Fine-tuning curves (the paper's fine-tuning figures): return vs fine-tuning frames.

One PNG per task, one line per method (named by :func:`dvfb.analysis.common.method_name`): the
mean over seeds of each ``curve.json`` evaluation, with a band: by default (``spread="ci"``) the
95% percentile interval of a seeded bootstrap of that mean (docs/reports.md), drawn only where
at least :data:`~dvfb.analysis.aggregate.MIN_RUNS_FOR_CI` seeds have the point; or ± the sample
std over seeds (ddof = 1, ``"std"``) or the standard error (``"se"``). Seeds need not share every
evaluation point: each point averages the seeds that have it. Figures are drawn with matplotlib's
object-oriented API on an Agg canvas (no pyplot state, no display needed).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dvfb.analysis.aggregate import mean_interval
from dvfb.analysis.common import AnalysisError, FinetuneEntry, method_sort_key
from dvfb.analysis.tables import STD_DDOF


@dataclass
class CurveBand:
    frames: np.ndarray
    mean: np.ndarray
    spread: np.ndarray  # NaN where only one seed has the point (and for "ci" bands)
    n: np.ndarray
    low: np.ndarray | None = None  # the band's edges (NaN: no band at the point)
    high: np.ndarray | None = None


def load_curves(runs: Sequence[FinetuneEntry], labels: Mapping[Path, str] | None = None
                ) -> dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """``{task: {method: [(frames, mean_return), ...one per run]}}`` from the runs' curve.json; a run
    whose curve file ``labels`` names is under that method (its table column, e.g. its budget's)."""
    curves: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        curve = run.run.curve(AnalysisError)  # the points' frames and returns are checked there
        if curve is None:
            continue
        if not curve.curve:
            raise AnalysisError(f"{run.run.curve_path}: 'curve' is missing or empty")
        frames = np.array([float(p["frames"]) for p in curve.curve])
        returns = np.array([float(p["mean_return"]) for p in curve.curve])
        curves[run.config.task][_label(run, labels)].append((frames, returns))
    return curves


def load_episode_curves(runs: Sequence[FinetuneEntry], labels: Mapping[Path, str] | None = None
                        ) -> dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """``{task: {method: [(episode, return), ...one per run]}}``: the return of every training
    episode of the protocols that record them (test-time search, online task inference), against
    the number of episodes of interaction (1, 2, ...); ``labels`` as :func:`load_curves`'."""
    curves: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        curve = run.run.curve(AnalysisError)
        if curve is None or not curve.episodes:
            continue
        returns = np.array([float(e["return"]) for e in curve.episodes])
        curves[run.config.task][_label(run, labels)].append((np.arange(1, len(returns) + 1, dtype=float), returns))
    return curves


def _label(run: FinetuneEntry, labels: Mapping[Path, str] | None) -> str:
    return (labels or {}).get(run.run.curve_path, run.method)


def aggregate(curves: Sequence[tuple[np.ndarray, np.ndarray]], spread: str = "std",
              bootstrap_seed: int = 0) -> CurveBand:
    """Mean and spread across runs at every frame count any run evaluated at. With
    ``spread="ci"`` the band is the bootstrap interval of the mean (``low``/``high``), NaN where
    fewer than MIN_RUNS_FOR_CI runs have the point."""
    frames = np.unique(np.concatenate([f for f, _ in curves]))
    mean, band, count, low, high = [], [], [], [], []
    for x in frames:
        values = np.array([r[f == x][0] for f, r in curves if np.any(f == x)])
        mean.append(values.mean())
        count.append(values.size)
        if spread == "ci":
            estimate = mean_interval(values, seed=bootstrap_seed)
            low.append(np.nan if estimate.low is None else estimate.low)
            high.append(np.nan if estimate.high is None else estimate.high)
            band.append(np.nan)
        elif values.size > 1:
            std = values.std(ddof=STD_DDOF)
            band.append(std / math.sqrt(values.size) if spread == "se" else std)
        else:
            band.append(float("nan"))
    mean_arr = np.array(mean)
    if spread != "ci":
        low, high = mean_arr - np.array(band), mean_arr + np.array(band)
    return CurveBand(frames, mean_arr, np.array(band), np.array(count), np.asarray(low, float), np.asarray(high, float))


def _plot_task(ax, task: str, by_method: dict[str, list], spread: str, seed: int = 0,
               xlabel: str = "fine-tuning frames") -> None:
    for method in sorted(by_method, key=method_sort_key):
        band = aggregate(by_method[method], spread, seed)
        seeds = len(by_method[method])
        (line,) = ax.plot(band.frames, band.mean, marker="o", markersize=3, label=f"{method} ({seeds} seed{'s' * (seeds != 1)})")
        ok = ~np.isnan(band.low)
        if ok.any():
            ax.fill_between(band.frames[ok], band.low[ok], band.high[ok], color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_title(task)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("episode return")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def plot_curves(curves: dict[str, dict[str, list]], out_dir: Path, spread: str = "ci", seed: int = 0,
                kind: str = "finetune") -> list[Path]:
    """``finetune_<task>.png`` per task and ``finetune_all.png`` (a grid of every task); with
    ``kind="episodes"``, the per-episode curves of :func:`load_episode_curves` as ``episodes_*.png``."""
    xlabel = "fine-tuning frames" if kind == "finetune" else "episodes of interaction"
    title = "Fine-tuning" if kind == "finetune" else "Returns of the episodes of interaction"
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.figure import Figure

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for task in sorted(curves):
        fig = Figure(figsize=(5, 3.6), dpi=100, layout="constrained")
        _plot_task(fig.add_subplot(), task, curves[task], spread, seed, xlabel)
        path = out_dir / f"{kind}_{task}.png"
        fig.savefig(path)
        written.append(path)
    if curves:
        tasks = sorted(curves)
        ncols = min(4, len(tasks))
        nrows = math.ceil(len(tasks) / ncols)
        fig = Figure(figsize=(4.5 * ncols, 3.4 * nrows), dpi=100, layout="constrained")
        what = {"se": "± standard error", "std": "± std", "ci": "with 95% bootstrap intervals (3+ seeds)"}[spread]
        fig.suptitle(f"{title}: mean episode return over seeds {what}")
        for i, task in enumerate(tasks):
            _plot_task(fig.add_subplot(nrows, ncols, i + 1), task, curves[task], spread, seed, xlabel)
        path = out_dir / f"{kind}_all.png"
        fig.savefig(path)
        written.append(path)
    return written
