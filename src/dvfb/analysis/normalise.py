"""Normalised scores: a return as a percentage of a reference on its task (docs/reports.md).

Three normalisers, each ``100 * (x - floor) / (ceiling - floor)`` per task:

* ``expert`` -- the URLB expert return (the paper's normalised scores; walker and quadruped only);
  floor 0;
* ``supervised`` -- the mean return of the supervised reference runs on the task (``dvfb
  supervised``: the DDPG core trained on the task's reward with the same frame budget, as "Does
  zero-shot RL exist?" scores methods against a supervised agent); floor 0;
* ``minmax`` -- random policy at 0 and supervised reference at 100: floor the mean return of the
  random-policy files, ceiling the supervised mean.

A task without its reference has no normalised score (a gap); a reference less than
:data:`MIN_RANGE` above the floor has none either, and the report says so rather than dividing by
it (a supervised agent that never reached a maze goal returns 1e-125, not 0: divided by that, a
baseline's 1e-60 became a score of 1e67).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from dvfb.analysis.common import AnalysisError, Score

# URLB expert returns (Laskin et al., 2021), used by the paper for its normalised scores.
EXPERT_RETURNS: dict[str, float] = {
    "walker_stand": 984.0, "walker_walk": 971.0, "walker_run": 796.0, "walker_flip": 799.0,
    "quadruped_stand": 920.0, "quadruped_walk": 866.0, "quadruped_jump": 888.0, "quadruped_run": 888.0,
}
SUPERVISED = "supervised"  # the method label of the supervised reference runs
RANDOM = "random"
# Columns that are references, not methods: they take no part in aggregates and comparisons.
REFERENCE_METHODS = (SUPERVISED, RANDOM)
NORMALISERS = ("expert", "supervised", "minmax")
CHOICES = ("auto", *NORMALISERS, "none")
# "auto" takes the first normaliser of this order that covers every task of the scores.
AUTO_ORDER = ("minmax", "supervised", "expert")
# The least ceiling - floor that normalises a task: far below any return a DMC agent earns by doing
# something (episodes run 0-1000) and below one success in 10 episodes (success rates run 0-1),
# far above the float dust of a reward that is a Gaussian tolerance of the distance to a goal.
MIN_RANGE = 0.01


@dataclass(frozen=True)
class Normaliser:
    """``100 * (x - floor[task]) / (ceiling[task] - floor[task])`` on the tasks it has."""

    name: str
    description: str
    ceiling: dict[str, float]
    floor: dict[str, float] = field(default_factory=dict)

    def covers(self, task: str) -> bool:
        return task in self.ceiling and self.ceiling[task] - self.floor.get(task, 0.0) >= MIN_RANGE

    def __call__(self, task: str, value: float) -> float:
        floor = self.floor.get(task, 0.0)
        return 100.0 * (value - floor) / (self.ceiling[task] - floor)

    def uncovered(self, tasks: Iterable[str]) -> list[str]:
        return [t for t in tasks if not self.covers(t)]


RAW = "raw episode returns (no normaliser covers every task)"
MIXED = "each domain's own scale, named under its heading (no one normaliser covers every domain)"


def scale_name(normaliser: Normaliser | None) -> str:
    """A scale's short name: the normaliser's, or raw episode returns."""
    return normaliser.name if normaliser is not None else "raw episode returns"


def describe_scale(normaliser: Normaliser | None) -> str:
    """A scale in the words of a report's caption."""
    return f"the {normaliser.name} normaliser: {normaliser.description}" if normaliser is not None else RAW


def _task_means(scores: Iterable[Score], method: str) -> dict[str, float]:
    values: dict[str, list[float]] = defaultdict(list)
    for score in scores:
        if score.method == method:
            values[score.task].append(score.value)
    return {task: float(np.mean(v)) for task, v in values.items()}


def normalisers(scores: Sequence[Score]) -> dict[str, Normaliser]:
    """The normalisers the scores allow: expert always; supervised and min-max where the scores
    include supervised-reference results (and, for min-max, random-policy results)."""
    out = {"expert": Normaliser("expert", "percent of the URLB expert return (walker stand/walk/run/flip "
                                "984/971/796/799, quadruped stand/walk/jump/run 920/866/888/888)",
                                dict(EXPERT_RETURNS))}
    supervised = _task_means(scores, SUPERVISED)
    if supervised:
        out["supervised"] = Normaliser("supervised", "percent of the supervised reference's mean return on the "
                                       "task (dvfb supervised, the same frame budget)", supervised)
        random = _task_means(scores, RANDOM)
        both = {t: v for t, v in supervised.items() if t in random}
        if both:
            out["minmax"] = Normaliser("minmax", "min-max score: 0 = the random policy's mean return, 100 = the "
                                       "supervised reference's", both, {t: random[t] for t in both})
    return out


def missing_reference(name: str, tasks: Sequence[str], available: dict[str, Normaliser]) -> str:
    """The one-line explanation of why ``name`` cannot normalise ``tasks``."""
    lacking = available[name].uncovered(tasks) if name in available else list(tasks)
    what = ", ".join(sorted(lacking))
    if name == "expert":
        return f"no URLB expert return for {what} (walker and quadruped tasks only); choose another --normaliser"
    fix = f"run `dvfb supervised --task TASK` for {what} (or agent 'supervised' in the sweep) and pass its runs"
    if name == "minmax":
        fix += "; min-max also needs --random files of those tasks"
    below = [t for t in lacking if name in available and t in available[name].ceiling]
    if below:
        return (f"the {name} reference is less than {MIN_RANGE} above its floor on {', '.join(below)}: "
                f"no {name} score")
    return f"no {name} reference for {what}: {fix}"


def choose(requested: str, tasks: Sequence[str], available: dict[str, Normaliser]) -> Normaliser | None:
    """The normaliser of the aggregates: ``requested`` (which must cover every task, else an
    :class:`AnalysisError` saying what is missing), the first of :data:`AUTO_ORDER` that does
    for ``auto``, or None (raw returns) for ``none`` or when no normaliser covers the tasks."""
    if requested not in CHOICES:
        raise AnalysisError(f"--normaliser must be one of {', '.join(CHOICES)}, got {requested!r}")
    if requested == "none":
        return None
    if requested != "auto":
        normaliser = available.get(requested)
        if normaliser is None or normaliser.uncovered(tasks):
            raise AnalysisError(missing_reference(requested, tasks, available))
        return normaliser
    for name in AUTO_ORDER:
        if name in available and not available[name].uncovered(tasks):
            return available[name]
    return None
