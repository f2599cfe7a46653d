"""Zero-shot over the pre-training budget (docs/reports.md, "Over the pre-training budget"): the
part of ``dvfb report`` that reads every snapshot's zero-shot results, not only the final one.

A run evaluated at several snapshots (``RUN/zeroshot/<task>@<frames>.json`` beside the final
``<task>.json``; a sweep's ``zeroshot_snapshots``) gives one point per snapshot. For each snapshot
and each domain this module computes

* Table 1 at that budget: the mean ± spread over seeds per task (:mod:`dvfb.analysis.tables`);
* the IQM over runs x tasks with its stratified bootstrap interval, per method
  (:mod:`dvfb.analysis.aggregate`), on one fixed scale for every snapshot: the domain's normaliser
  in the report's final-snapshot aggregates (the supervised reference and the random policy at the
  final budget), so that a rising curve is a real gain and not a moving yardstick;
* the probability that the focal method (DVFB when the runs have it) beats each other method;
* the methods ranked by IQM,

and draws the IQM against the pre-training frames, one panel per domain with the interval as a
band (the shape of the paper's Figure 3(a)). Nothing is computed unless some method has results at
two snapshots or more.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dvfb.analysis import aggregate as agg
from dvfb.analysis.aggregate_report import BootstrapConfig
from dvfb.analysis.common import RETURN, AnalysisError, PretrainEntry, Score, method_sort_key, zeroshot_scores
from dvfb.analysis.normalise import MIXED, RANDOM, RAW, REFERENCE_METHODS, SUPERVISED, Normaliser, scale_name
from dvfb.analysis.tables import Table, build_table, sample_sizes, to_markdown

TITLE = "Zero-shot over the pre-training budget"
FOCUS = "dvfb"  # the method whose probability of improvement over each other one is reported


def snapshot_scores(runs: Iterable[PretrainEntry], metric: str = RETURN) -> list[Score]:
    """One score per run, task and snapshot: every zero-shot result of the runs, the earlier
    snapshots' ``<task>@<frames>.json`` as well as the final ``<task>.json``. A result that does not
    record its snapshot's frames cannot be placed on the budget axis and is left out."""
    return [s for s in zeroshot_scores(runs, metric, every_snapshot=True) if s.pretrain_frames is not None]


@dataclass
class Point:
    """One method at one snapshot in one domain."""

    frames: int
    iqm: agg.Estimate
    runs_per_task: int


@dataclass
class Domain:
    """The budget curves of one domain."""

    name: str
    tasks: list[str]
    curves: dict[str, list[Point]] = field(default_factory=dict)  # method -> points by frames
    # (frames, other method) -> P(focus > other)
    improvement: dict[tuple[int, str], agg.Estimate] = field(default_factory=dict)
    ranking: dict[int, list[str]] = field(default_factory=dict)  # frames -> methods by IQM, best first
    tables: dict[int, Table] = field(default_factory=dict)  # frames -> Table 1 at that budget
    dropped: list[str] = field(default_factory=list)  # tasks not every method has at every snapshot
    normaliser: Normaliser | None = None  # the scale of its curves (None: raw episode returns)

    @property
    def unit(self) -> str:
        return f"{self.normaliser.name}-normalised score" if self.normaliser is not None else "episode return"


@dataclass
class Budget:
    focus: str | None
    frames: list[int]
    domains: list[Domain]
    notes: list[str] = field(default_factory=list)

    @property
    def uniform(self) -> bool:
        """Whether every domain's curves are on one scale."""
        return len({scale_name(d.normaliser) for d in self.domains}) <= 1


def has_budget_axis(scores: Sequence[Score]) -> bool:
    """Whether some method (not a reference) has results at two snapshots or more."""
    frames: dict[str, set[int]] = {}
    for s in scores:
        if s.method not in REFERENCE_METHODS and s.pretrain_frames is not None:
            frames.setdefault(s.method, set()).add(s.pretrain_frames)
    return any(len(f) > 1 for f in frames.values())


def compute(scores: Sequence[Score], random: Sequence[Score], normalisers: Mapping[str, Normaliser | None],
            spread: str = "std", bootstrap: BootstrapConfig | None = None) -> Budget | None:
    """The budget curves of ``scores`` (from :func:`snapshot_scores`), each domain on its scale in
    ``normalisers`` (the final-snapshot aggregates' normaliser of that domain; None or absent: raw
    returns); ``random`` (random-policy scores) only joins the per-snapshot tables. None when no
    method has two snapshots."""
    if not has_budget_axis(scores):
        return None
    bootstrap = bootstrap or BootstrapConfig()
    methods = {s.method for s in scores if s.method not in REFERENCE_METHODS}
    focus = FOCUS if FOCUS in methods else None
    frames = sorted({s.pretrain_frames for s in scores if s.method not in REFERENCE_METHODS})
    domains = []
    notes = []
    for domain in _in_order(s.domain for s in scores if s.method not in REFERENCE_METHODS):
        in_domain = [s for s in scores if s.domain == domain]
        # The supervised reference's own curve is a method here: how far the same frames of
        # supervised learning on each task get.
        as_methods = [s if s.method != SUPERVISED else _as_method(s) for s in in_domain]
        every = sorted({s.task for s in as_methods if s.method not in REFERENCE_METHODS})
        shared = agg.common_tasks([s for s in as_methods if s.method != RANDOM])
        shared = [t for t in shared if all(_has_task(as_methods, t, f, m)
                                           for f in frames for m in _methods_at(as_methods, f))]
        normaliser = normalisers.get(domain)
        result = Domain(domain, shared, dropped=[t for t in every if t not in shared], normaliser=normaliser)
        if result.dropped:
            notes.append(f"{domain}: {', '.join(result.dropped)} left out of the budget curves (not every method "
                         "has them at every snapshot)")
        for f in frames:
            at = [s for s in as_methods if s.pretrain_frames == f]
            if not at:
                continue
            tables_input = [s for s in in_domain if s.pretrain_frames == f] + [s for s in random if s.domain == domain]
            result.tables[f] = build_table(tables_input, f"Table 1 at {f:,} pre-training frames: {domain}", spread)
            if not shared:
                continue
            matrices = agg.score_matrices(at, normaliser, shared)
            for method, matrix in matrices.items():
                estimate = agg.aggregate_metrics(matrix, samples=bootstrap.samples, confidence=bootstrap.confidence,
                                                 seed=bootstrap.seed)["iqm"]
                result.curves.setdefault(method, []).append(Point(f, estimate, matrix.min_runs))
            result.ranking[f] = sorted(matrices, key=lambda m: (-_iqm_at(result, m, f), method_sort_key(m)))
            if focus in matrices:
                for other in sorted(matrices, key=method_sort_key):
                    if other != focus:
                        result.improvement[(f, other)] = agg.probability_of_improvement(
                            matrices[focus], matrices[other], samples=bootstrap.samples,
                            confidence=bootstrap.confidence, seed=bootstrap.seed)
        domains.append(result)
    thin = sorted({m for d in domains for m, points in d.curves.items() if any(p.runs_per_task < agg.MIN_RUNS_FOR_CI
                                                                                 for p in points)})
    if thin:
        notes.append(f"budget curves: fewer than {agg.MIN_RUNS_FOR_CI} runs per task for {', '.join(thin)}: no "
                     "interval at those points")
    return Budget(focus, frames, domains, notes)


def _as_method(score: Score) -> Score:
    # A supervised run learns one task: its cells are named per task, the column is "supervised".
    return Score(score.kind, "supervised (same frames)", score.domain, score.task, score.seed, score.value,
                 score.source, score.frames, score.pretrain_frames, score.episodes)


def _methods_at(scores: Sequence[Score], frames: int) -> set[str]:
    return {s.method for s in scores if s.pretrain_frames == frames and s.method not in REFERENCE_METHODS}


def _has_task(scores: Sequence[Score], task: str, frames: int, method: str) -> bool:
    return any(s.task == task and s.pretrain_frames == frames and s.method == method for s in scores)


def _iqm_at(domain: Domain, method: str, frames: int) -> float:
    return next(p.iqm.value for p in domain.curves[method] if p.frames == frames)


def _in_order(names: Iterable[str]) -> list[str]:
    seen: list[str] = []
    for name in names:
        if name not in seen:
            seen.append(name)
    return seen


# ---------------------------------------------------------------------------------------------
# output


def _estimate(e: agg.Estimate, digits: int = 1) -> str:
    if not e.has_interval:
        return f"{e.value:.{digits}f}"
    return f"{e.value:.{digits}f} [{e.low:.{digits}f}, {e.high:.{digits}f}]"


def _scale(normaliser: Normaliser | None) -> str:
    return (f"the {normaliser.name} normaliser of the final snapshot ({normaliser.description}), the same for "
            "every snapshot" if normaliser is not None else RAW)


def markdown(budget: Budget, bootstrap: BootstrapConfig, figure: str | None, heading_level: int = 2) -> str:
    hashes = "#" * heading_level
    level = int(round(100 * bootstrap.confidence))
    scale = _scale(budget.domains[0].normaliser) if budget.uniform and budget.domains else MIXED
    parts = [f"{hashes} {TITLE}", "",
             f"Every snapshot's zero-shot results. IQM over runs × tasks on {scale}, with its {level}% interval "
             f"of a stratified bootstrap ({bootstrap.samples} resamples, seed {bootstrap.seed}); no interval where "
             f"a method has fewer than {agg.MIN_RUNS_FOR_CI} runs on a task. `supervised (same frames)` is the "
             "supervised reference's own snapshot at that budget.", ""]
    if figure:
        parts += [f"![{TITLE}]({figure})", ""]
    for domain in budget.domains:
        frames = [f for f in budget.frames if any(p.frames == f for pts in domain.curves.values() for p in pts)]
        parts += [f"{hashes}# {domain.name}", ""]
        if not budget.uniform:
            parts += [f"On {_scale(domain.normaliser)}.", ""]
        if domain.curves:
            parts += [f"IQM by pre-training frames (tasks: {', '.join(domain.tasks)}):", "",
                      "| method | " + " | ".join(f"{f:,}" for f in frames) + " |", "|---|" + "---:|" * len(frames)]
            for method in sorted(domain.curves, key=method_sort_key):
                by_frames = {p.frames: p for p in domain.curves[method]}
                parts.append(f"| {method} | " + " | ".join(_estimate(by_frames[f].iqm) if f in by_frames else "–"
                                                           for f in frames) + " |")
            parts += ["", "Ranking by IQM (best first):", ""]
            parts += [f"- {f:,} frames: " + " > ".join(domain.ranking[f]) for f in frames if f in domain.ranking]
            parts.append("")
        others = sorted({other for (_, other) in domain.improvement}, key=method_sort_key)
        if others:
            parts += [f"P({budget.focus} > column), per task the chance that a random {budget.focus} run scores "
                      "above one of the column (ties count a half), averaged over the tasks:", "",
                      "| frames | " + " | ".join(others) + " |", "|---|" + "---:|" * len(others)]
            for f in frames:
                parts.append(f"| {f:,} | " + " | ".join(_estimate(domain.improvement[(f, o)], 2)
                                                        if (f, o) in domain.improvement else "–" for o in others) + " |")
            parts.append("")
        for f in sorted(domain.tables):
            table = domain.tables[f]
            parts += [f"{hashes}## {table.title}", "", f"Episode return: mean ± {table.spread} over seeds. "
                      f"{sample_sizes(table)}", "", to_markdown(table), ""]
    if budget.notes:
        parts += ["Notes:", ""] + [f"- {note}" for note in budget.notes] + [""]
    return "\n".join(parts)


def to_csv(budget: Budget) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["domain", "frames", "method", "metric", "value", "low", "high", "runs_per_task", "tasks",
                     "normaliser"])
    for domain in budget.domains:
        scale = domain.normaliser.name if domain.normaliser is not None else "none"
        for method in sorted(domain.curves, key=method_sort_key):
            for p in domain.curves[method]:
                writer.writerow([domain.name, p.frames, method, "iqm", repr(p.iqm.value), _bound(p.iqm.low),
                                 _bound(p.iqm.high), p.runs_per_task, " ".join(domain.tasks), scale])
        for (frames, other), e in sorted(domain.improvement.items(), key=lambda kv: (kv[0][0], method_sort_key(kv[0][1]))):
            writer.writerow([domain.name, frames, f"{budget.focus} > {other}", "probability_of_improvement",
                             repr(e.value), _bound(e.low), _bound(e.high), "", " ".join(domain.tasks), scale])
    return out.getvalue()


def _bound(x: float | None) -> str:
    return "" if x is None else repr(x)


def plot(budget: Budget, path: Path, confidence: float) -> Path:
    """One panel per domain: each method's IQM against the pre-training frames, its interval as a band."""
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.figure import Figure

    domains = [d for d in budget.domains if d.curves]
    if not domains:
        raise AnalysisError("no domain has budget curves to draw")
    n = len(domains)
    fig = Figure(figsize=(max(6.5, 5.4 * n), 4.4), dpi=100, layout="constrained")
    unit = domains[0].unit if budget.uniform else "score (each panel's scale)"
    fig.suptitle(f"{TITLE}: IQM of the {unit}\n({int(round(100 * confidence))}% stratified bootstrap bands)",
                 fontsize=11)
    for i, domain in enumerate(domains):
        ax = fig.add_subplot(1, n, i + 1)
        for method in sorted(domain.curves, key=method_sort_key):
            points = domain.curves[method]
            x = [p.frames for p in points]
            style = "--" if method.startswith("supervised") else "-"
            (line,) = ax.plot(x, [p.iqm.value for p in points], style, marker="o", label=method)
            if all(p.iqm.has_interval for p in points):
                ax.fill_between(x, [p.iqm.low for p in points], [p.iqm.high for p in points], color=line.get_color(),
                                alpha=0.18, linewidth=0)
        if domain.normaliser is not None and domain.normaliser.floor:
            ax.axhline(0.0, color="grey", linewidth=0.8, linestyle=":", label="random policy")
        ax.set_title(domain.name)
        ax.set_xlabel("pre-training frames")
        ax.set_ylabel(f"IQM ({domain.unit})")
        ax.set_xticks(budget.frames)
        ax.set_xticklabels([f"{f // 1000}k" if f % 1000 == 0 else str(f) for f in budget.frames])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
