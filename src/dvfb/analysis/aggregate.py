"""Aggregate metrics over runs x tasks with stratified bootstrap confidence intervals
(docs/reports.md; Agarwal et al., NeurIPS 2021, "Deep RL at the Edge of the Statistical Precipice").

A method's results form a score matrix: for every task, the (normalised) scores of its runs
(seeds). Every aggregate is defined as rliable 1.2.0 defines it (the tests compare them):

* ``iqm`` -- the interquartile mean: the mean of the middle 50% of all runs x tasks scores
  (``scipy.stats.trim_mean(x, 0.25)``);
* ``mean`` and ``median`` -- the mean and the median over tasks of each task's mean score over
  its runs (with equal runs per task, the mean equals the mean of all scores; the median does not
  equal the median of all scores);
* ``optimality_gap`` -- the mean shortfall of all scores below the normaliser's 100,
  ``mean(max(100 - x, 0))`` (lower is better);
* the probability of improvement ``P(X > Y)`` of one method over another: per task, the chance
  that a random run of X scores above a random run of Y (ties count a half), averaged over tasks;
* a performance profile: for each threshold ``tau``, the fraction of runs x tasks scoring above it.

Confidence intervals are percentile intervals of a **stratified** bootstrap: each task's runs are
resampled with replacement on their own (the task is the stratum), which is
``scipy.stats.bootstrap`` with every task's runs passed as a separate sample. The bootstrap is
seeded: the same inputs and seed give the same intervals. With fewer than
:data:`MIN_RUNS_FOR_CI` runs on some task, a resample can only repeat a handful of values and
its interval says nothing; no interval is computed then and the report says why.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from dvfb.analysis.common import Score
from dvfb.analysis.normalise import REFERENCE_METHODS, Normaliser
from dvfb.envs import TASKS

METRICS = ("iqm", "mean", "median", "optimality_gap")
METRIC_TITLES = {"iqm": "IQM", "mean": "mean", "median": "median", "optimality_gap": "optimality gap"}
MIN_RUNS_FOR_CI = 3
BOOTSTRAP_SAMPLES = 2000
CONFIDENCE = 0.95
GAP_THRESHOLD = 100.0  # the normalised score of the reference


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return stats.trim_mean(x, 0.25, axis=axis)


def optimality_gap(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(np.maximum(GAP_THRESHOLD - x, 0.0), axis=axis)


METRIC_FUNCTIONS: dict[str, Callable[..., np.ndarray]] = {
    "iqm": iqm, "mean": np.mean, "median": np.median, "optimality_gap": optimality_gap}
# Metrics of the per-task mean scores (rliable's aggregate_mean and aggregate_median); the others
# pool all runs x tasks scores.
OF_TASK_MEANS = frozenset({"mean", "median"})


@dataclass(frozen=True)
class Estimate:
    """A point estimate and its confidence interval (None: not computed, too few runs)."""

    value: float
    low: float | None = None
    high: float | None = None

    @property
    def has_interval(self) -> bool:
        return self.low is not None


@dataclass
class ScoreMatrix:
    """One method's scores: ``columns[i]`` holds the runs' scores on ``tasks[i]``."""

    method: str
    tasks: list[str]
    columns: list[np.ndarray]

    @property
    def min_runs(self) -> int:
        return min(len(c) for c in self.columns)

    @property
    def flat(self) -> np.ndarray:
        return np.concatenate(self.columns)

    @property
    def can_bootstrap(self) -> bool:
        return self.min_runs >= MIN_RUNS_FOR_CI


def score_matrices(scores: Sequence[Score], normaliser: Normaliser | None,
                   tasks: Sequence[str] | None = None) -> dict[str, ScoreMatrix]:
    """The score matrix of every method (not the reference columns) over ``tasks`` (default: the
    tasks every method has), normalised by ``normaliser`` (None: raw returns)."""
    by_method: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for score in scores:
        if score.method in REFERENCE_METHODS:
            continue
        value = normaliser(score.task, score.value) if normaliser is not None else score.value
        by_method[score.method][score.task].append(value)
    if tasks is None:
        tasks = common_tasks(scores)
    return {method: ScoreMatrix(method, list(tasks), [np.asarray(per_task[t], dtype=float) for t in tasks])
            for method, per_task in by_method.items() if tasks and all(t in per_task for t in tasks)}


def common_tasks(scores: Sequence[Score]) -> list[str]:
    """The tasks every method (not the references) has a result on, in first-seen order."""
    per_method: dict[str, set[str]] = defaultdict(set)
    order: list[str] = []
    for score in scores:
        if score.method in REFERENCE_METHODS:
            continue
        per_method[score.method].add(score.task)
        if score.task not in order:
            order.append(score.task)
    if not per_method:
        return []
    shared = set.intersection(*per_method.values())
    return sorted((t for t in order if t in shared), key=_task_order)


def _task_order(task: str) -> tuple:
    """Registry order (docs/tasks.md), unknown tasks last by name."""

    names = list(TASKS)
    return (names.index(task), "") if task in names else (len(names), task)


def stratified_interval(columns: Sequence[np.ndarray], statistic: Callable[..., np.ndarray], *,
                        samples: int = BOOTSTRAP_SAMPLES, confidence: float = CONFIDENCE,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The percentile interval of ``statistic(*columns, axis=-1)`` under the stratified bootstrap:
    each column resampled with replacement on its own."""
    result = stats.bootstrap(tuple(np.asarray(c, dtype=float) for c in columns), statistic,
                             n_resamples=samples, confidence_level=confidence, method="percentile",
                             vectorized=True, rng=np.random.default_rng(seed))
    return np.asarray(result.confidence_interval.low), np.asarray(result.confidence_interval.high)


def _pooled(metric: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    def statistic(*columns: np.ndarray, axis: int = -1) -> np.ndarray:
        return metric(np.concatenate(columns, axis=axis), axis=axis)
    return statistic


def _of_task_means(metric: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    def statistic(*columns: np.ndarray, axis: int = -1) -> np.ndarray:
        return metric(np.stack([c.mean(axis=axis) for c in columns], axis=-1), axis=-1)
    return statistic


def metric_statistic(name: str) -> Callable[..., np.ndarray]:
    """``statistic(*columns, axis=-1)`` of the metric ``name`` over a matrix's columns."""
    metric = METRIC_FUNCTIONS[name]
    return _of_task_means(metric) if name in OF_TASK_MEANS else _pooled(metric)


def aggregate_metrics(matrix: ScoreMatrix, *, samples: int = BOOTSTRAP_SAMPLES, confidence: float = CONFIDENCE,
                      seed: int = 0) -> dict[str, Estimate]:
    """IQM, mean, median and optimality gap of the matrix, with intervals when it has the runs."""
    out = {}
    for name in METRICS:
        statistic = metric_statistic(name)
        value = float(statistic(*matrix.columns))
        if matrix.can_bootstrap:
            low, high = stratified_interval(matrix.columns, statistic, samples=samples,
                                            confidence=confidence, seed=seed)
            out[name] = Estimate(value, float(low), float(high))
        else:
            out[name] = Estimate(value)
    return out


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y) / 2 over all pairs of the last axes' runs (batched over leading axes)."""
    diff = x[..., :, None] - y[..., None, :]
    return np.mean((diff > 0) + 0.5 * (diff == 0), axis=(-2, -1))


def probability_of_improvement(x: ScoreMatrix, y: ScoreMatrix, *, samples: int = BOOTSTRAP_SAMPLES,
                               confidence: float = CONFIDENCE, seed: int = 0) -> Estimate:
    """P(X > Y) averaged over the tasks both matrices share (in ``x``'s order)."""
    tasks = [t for t in x.tasks if t in y.tasks]
    xs = [x.columns[x.tasks.index(t)] for t in tasks]
    ys = [y.columns[y.tasks.index(t)] for t in tasks]
    value = float(np.mean([_improvement(a, b) for a, b in zip(xs, ys)]))
    if min(x.min_runs, y.min_runs) < MIN_RUNS_FOR_CI:
        return Estimate(value)
    n = len(tasks)

    def statistic(*columns: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean([_improvement(columns[i], columns[n + i]) for i in range(n)], axis=0)

    low, high = stratified_interval([*xs, *ys], statistic, samples=samples, confidence=confidence, seed=seed)
    return Estimate(value, float(low), float(high))


@dataclass
class Profile:
    """A performance profile: the fraction of runs x tasks above each threshold, with its band
    (None when the matrix has too few runs)."""

    method: str
    thresholds: np.ndarray
    fraction: np.ndarray
    low: np.ndarray | None
    high: np.ndarray | None


def performance_profile(matrix: ScoreMatrix, thresholds: np.ndarray, *, samples: int = BOOTSTRAP_SAMPLES,
                        confidence: float = CONFIDENCE, seed: int = 0) -> Profile:
    thresholds = np.asarray(thresholds, dtype=float)

    def above(x: np.ndarray, axis: int = -1) -> np.ndarray:
        # (..., n) -> (thresholds, ...): scipy takes the statistic's extra output axis first.
        return np.moveaxis(np.mean(x[..., None, :] > thresholds[:, None], axis=-1), -1, 0)

    fraction = above(matrix.flat)
    if not matrix.can_bootstrap:
        return Profile(matrix.method, thresholds, fraction, None, None)
    low, high = stratified_interval(matrix.columns, _pooled(above), samples=samples, confidence=confidence, seed=seed)
    return Profile(matrix.method, thresholds, fraction, low, high)


def mean_interval(values: np.ndarray, *, samples: int = BOOTSTRAP_SAMPLES, confidence: float = CONFIDENCE,
                  seed: int = 0) -> Estimate:
    """The mean of one sample and its bootstrap interval (the fine-tuning curves' bands)."""
    values = np.asarray(values, dtype=float)
    if values.size < MIN_RUNS_FOR_CI:
        return Estimate(float(values.mean()))
    low, high = stratified_interval([values], _pooled(np.mean), samples=samples, confidence=confidence, seed=seed)
    return Estimate(float(values.mean()), float(low), float(high))
