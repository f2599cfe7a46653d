"""The aggregate part of ``dvfb report`` (docs/reports.md): per scope (every domain together, and
each domain), a table of IQM, mean, median and optimality gap with stratified bootstrap
intervals, the probability of improvement of every pair of methods, and a performance-profile
figure, all on one normaliser's scores (:mod:`dvfb.analysis.normalise`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dvfb.analysis import aggregate as agg
from dvfb.analysis.common import Score, method_sort_key
from dvfb.analysis.normalise import (MIXED, REFERENCE_METHODS, SUPERVISED, Normaliser, choose, describe_scale,
                                    missing_reference, scale_name)
from dvfb.analysis.normalise import normalisers as available_normalisers

ALL_DOMAINS = "all domains"
PROFILE_POINTS = 101


@dataclass
class BootstrapConfig:
    samples: int = agg.BOOTSTRAP_SAMPLES
    confidence: float = agg.CONFIDENCE
    seed: int = 0


@dataclass
class Scope:
    """The aggregates of one scope (a domain, or every domain)."""

    name: str
    tasks: list[str]
    matrices: dict[str, agg.ScoreMatrix]
    metrics: dict[str, dict[str, agg.Estimate]] = field(default_factory=dict)
    improvement: dict[tuple[str, str], agg.Estimate] = field(default_factory=dict)
    profiles: dict[str, agg.Profile] = field(default_factory=dict)
    dropped: list[str] = field(default_factory=list)  # tasks some method lacks
    normaliser: Normaliser | None = None  # the scale of its scores (None: raw episode returns)

    @property
    def unit(self) -> str:
        return "normalised score" if self.normaliser is not None else "episode return"


@dataclass
class Aggregates:
    kind: str  # "zeroshot" or "finetune"
    title: str
    scopes: list[Scope]
    notes: list[str] = field(default_factory=list)

    @property
    def uniform(self) -> bool:
        """Whether every scope is on one scale."""
        return len({scale_name(scope.normaliser) for scope in self.scopes}) <= 1

    @property
    def normaliser(self) -> Normaliser | None:
        """Every scope's normaliser when they share one; else None (each Scope has its own)."""
        return self.scopes[0].normaliser if self.scopes and self.uniform else None


def _domains(scores: Sequence[Score]) -> list[str]:
    seen: list[str] = []
    for s in scores:
        if s.domain not in seen:
            seen.append(s.domain)
    return seen


def compute(scores: Sequence[Score], kind: str, title: str, requested: str = "auto",
            bootstrap: BootstrapConfig | None = None) -> Aggregates | None:
    """The aggregates of a table's scores; None when fewer than one method (beside the
    references) has results. Raises AnalysisError when an explicitly requested normaliser lacks
    a reference. With ``auto``, each domain takes the first normaliser that covers its own tasks
    (walker min-max beside a maze on raw returns, say), and the every-domain scope exists only
    when the domains share one."""
    bootstrap = bootstrap or BootstrapConfig()
    methods = {s.method for s in scores if s.method not in REFERENCE_METHODS}
    if not methods:
        return None
    available = available_normalisers(scores)
    tasks = sorted({s.task for s in scores if s.method not in REFERENCE_METHODS})
    normaliser = choose(requested, tasks, available)
    domains = _domains([s for s in scores if s.method not in REFERENCE_METHODS])
    groups = [(d, [s for s in scores if s.domain == d]) for d in domains]
    domain_tasks = {d: sorted({s.task for s in group if s.method not in REFERENCE_METHODS}) for d, group in groups}
    scales = {d: choose("auto", domain_tasks[d], available) if requested == "auto" else normaliser for d in domains}
    uniform = len({scale_name(n) for n in scales.values()}) == 1
    notes = []
    lacking_by_scope = [(None, tasks, normaliser)] if uniform else [(d, domain_tasks[d], scales[d]) for d in domains]
    for scope_name, scope_tasks, chosen in lacking_by_scope if requested == "auto" else ():
        prefix = f"{scope_name}: " if scope_name else ""
        if kind == "finetune" and SUPERVISED not in {s.method for s in scores}:
            # The supervised reference is a zero-shot result (docs/reports.md): telling the user to run it
            # would not change the fine-tuning aggregates, so the note says which normaliser applies.
            if chosen is None:
                notes.append(f"{prefix}fine-tuning aggregates are over raw episode returns: "
                             + missing_reference("expert", scope_tasks, available))
            else:
                notes.append(f"{prefix}fine-tuning aggregates use the {chosen.name} normaliser (the supervised "
                             "reference normalises zero-shot results only)")
        elif chosen is None:
            notes.append(f"{prefix}aggregates are over raw episode returns: "
                         + missing_reference("supervised", scope_tasks, available))
        elif chosen.name != "minmax":
            lacking = "supervised" if chosen.name == "expert" else "minmax"
            notes.append(f"{prefix}aggregates use the {chosen.name} normaliser: "
                         + missing_reference(lacking, scope_tasks, available))
    if len(domains) > 1:
        if uniform:
            groups.insert(0, (ALL_DOMAINS, list(scores)))
            scales[ALL_DOMAINS] = next(iter(scales.values()))
        else:
            notes.append("no aggregate over all domains: their scores are on different scales ("
                         + ", ".join(f"{d}: {scale_name(scales[d])}" for d in domains) + ")")
    scopes = []
    for name, group in groups:
        shared = agg.common_tasks(group)
        every = sorted({s.task for s in group if s.method not in REFERENCE_METHODS})
        scope = Scope(name, shared, agg.score_matrices(group, scales[name], shared),
                      dropped=[t for t in every if t not in shared], normaliser=scales[name])
        if not scope.matrices:
            continue
        _fill(scope, bootstrap)
        scopes.append(scope)
        if scope.dropped:
            notes.append(f"{name}: {', '.join(scope.dropped)} left out of the aggregates (not every method has them)")
        thin = sorted(m for m, matrix in scope.matrices.items() if not matrix.can_bootstrap)
        if thin:
            notes.append(f"{name}: fewer than {agg.MIN_RUNS_FOR_CI} runs on some task for {', '.join(thin)}: "
                         "no confidence intervals (with so few runs they are not meaningful)")
    return Aggregates(kind, title, scopes, notes)


def _metrics(scope: Scope) -> tuple[str, ...]:
    # The optimality gap is the shortfall below a normaliser's 100: raw returns have no such line.
    return agg.METRICS if scope.normaliser is not None else tuple(m for m in agg.METRICS if m != "optimality_gap")


def _fill(scope: Scope, b: BootstrapConfig) -> None:
    methods = sorted(scope.matrices, key=method_sort_key)
    for method in methods:
        scope.metrics[method] = agg.aggregate_metrics(scope.matrices[method], samples=b.samples,
                                                      confidence=b.confidence, seed=b.seed)
    for x in methods:
        for y in methods:
            if x != y:
                scope.improvement[(x, y)] = agg.probability_of_improvement(
                    scope.matrices[x], scope.matrices[y], samples=b.samples, confidence=b.confidence, seed=b.seed)
    flat = np.concatenate([m.flat for m in scope.matrices.values()])
    high = max(100.0, float(flat.max())) if scope.normaliser is not None else float(flat.max())
    low = min(0.0, float(flat.min()))
    thresholds = np.linspace(low, high, PROFILE_POINTS)
    for method in methods:
        scope.profiles[method] = agg.performance_profile(scope.matrices[method], thresholds, samples=b.samples,
                                                         confidence=b.confidence, seed=b.seed)


# ---------------------------------------------------------------------------------------------
# output


def _estimate(e: agg.Estimate, digits: int = 1) -> str:
    if not e.has_interval:
        return f"{e.value:.{digits}f}"
    return f"{e.value:.{digits}f} [{e.low:.{digits}f}, {e.high:.{digits}f}]"


def markdown(result: Aggregates, bootstrap: BootstrapConfig, figure: str | None, heading_level: int = 2) -> str:
    hashes = "#" * heading_level
    level = int(round(100 * bootstrap.confidence))
    scale = describe_scale(result.normaliser) if result.uniform else MIXED
    parts = [f"{hashes} {result.title}: aggregates", "",
             f"Over runs × tasks, on {scale}. Point estimate [{level}% interval of a stratified bootstrap: "
             f"{bootstrap.samples} resamples, each task's runs resampled on their own, seed {bootstrap.seed}]. "
             f"Optimality gap: mean shortfall below 100 (lower is better; normalised scores only). No interval where a method has "
             f"fewer than {agg.MIN_RUNS_FOR_CI} runs on a task.", ""]
    for scope in result.scopes:
        methods = sorted(scope.matrices, key=method_sort_key)
        metrics = _metrics(scope)
        parts += [f"{hashes}# {scope.name}", ""]
        if not result.uniform:
            parts += [f"On {describe_scale(scope.normaliser)}.", ""]
        parts += [f"Tasks: {', '.join(scope.tasks)}. " + "; ".join(
                      f"{m} {scope.matrices[m].min_runs} run{'s' if scope.matrices[m].min_runs != 1 else ''}/task"
                      for m in methods) + ".", "",
                  "| method | " + " | ".join(agg.METRIC_TITLES[k] for k in metrics) + " |",
                  "|---|" + "---:|" * len(metrics)]
        for m in methods:
            parts.append(f"| {m} | " + " | ".join(_estimate(scope.metrics[m][k]) for k in metrics) + " |")
        if len(methods) > 1:
            parts += ["", "Probability of improvement P(row > column): per task, the chance that a random run of "
                      "the row scores above one of the column (ties count a half), averaged over the tasks.", "",
                      "| P(row > column) | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
            for x in methods:
                cells = ["–" if x == y else _estimate(scope.improvement[(x, y)], 2) for y in methods]
                parts.append(f"| {x} | " + " | ".join(cells) + " |")
        parts.append("")
    if figure:
        parts += [f"Performance profiles: ![performance profile]({figure})", ""]
    return "\n".join(parts)


def to_csv(result: Aggregates) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["scope", "method", "metric", "value", "low", "high", "runs_per_task", "tasks", "normaliser"])
    for scope in result.scopes:
        for method in sorted(scope.matrices, key=method_sort_key):
            for metric in _metrics(scope):
                e = scope.metrics[method][metric]
                writer.writerow([scope.name, method, metric, repr(e.value), "" if e.low is None else repr(e.low),
                                 "" if e.high is None else repr(e.high), scope.matrices[method].min_runs,
                                 " ".join(scope.tasks), scope.normaliser.name if scope.normaliser else "none"])
        for (x, y), e in scope.improvement.items():
            writer.writerow([scope.name, f"{x} > {y}", "probability_of_improvement", repr(e.value),
                             "" if e.low is None else repr(e.low), "" if e.high is None else repr(e.high),
                             min(scope.matrices[x].min_runs, scope.matrices[y].min_runs), " ".join(scope.tasks),
                             scope.normaliser.name if scope.normaliser else "none"])
    return out.getvalue()


def plot_profiles(result: Aggregates, path: Path, confidence: float) -> Path:
    """One panel per scope: the fraction of runs x tasks above each threshold, with its band."""
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.figure import Figure

    n = len(result.scopes)
    fig = Figure(figsize=(max(6.5, 5.2 * n), 4.2), dpi=100, layout="constrained")
    fig.suptitle(f"{result.title}: performance profiles\n({int(round(100 * confidence))}% stratified bootstrap bands)",
                 fontsize=11)
    for i, scope in enumerate(result.scopes):
        ax = fig.add_subplot(1, n, i + 1)
        for method in sorted(scope.profiles, key=method_sort_key):
            p = scope.profiles[method]
            (line,) = ax.plot(p.thresholds, p.fraction, label=f"{method} ({scope.matrices[method].min_runs} runs/task)")
            if p.low is not None:
                ax.fill_between(p.thresholds, p.low, p.high, color=line.get_color(), alpha=0.2, linewidth=0)
        ax.set_title(scope.name)
        ax.set_xlabel(f"{scope.unit} τ" + (f" ({scope.normaliser.name})" if scope.normaliser else ""))
        ax.set_ylabel("fraction of runs × tasks with score > τ")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
