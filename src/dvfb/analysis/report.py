"""``dvfb report``: the paper's Table 1 (zero-shot), Table 2 (fine-tuning), Table 6 (success rates)
and fine-tuning curves.

Inputs are run directories or directories of runs (see :func:`dvfb.analysis.common.discover_runs`)
and optional random-policy files. Outputs, in ``out_dir``:

* ``report.md`` -- both tables (raw returns and expert-normalised), notes, links to the curves;
* ``table1_zeroshot.md/.csv`` and ``table1_zeroshot_normalised.csv`` (when zero-shot results exist);
* ``table2_finetune.md/.csv`` and ``table2_finetune_normalised.csv`` (when fine-tuning runs exist);
* ``table6_success.md`` with ``table6_success_zeroshot.csv`` and ``table6_success_finetune.csv``
  (when results carry success rates: the Meta-World tasks, docs/tasks.md §4.6);
* ``curves/finetune_<task>.png`` and ``curves/finetune_all.png`` (when fine-tuning runs exist);
* the normalised tables of every normaliser the inputs allow (``table1_zeroshot_supervised.csv``,
  ``table1_zeroshot_minmax.csv``, likewise for Table 2; :mod:`dvfb.analysis.normalise`);
* ``aggregates_<kind>.md/.csv`` and ``profiles_<kind>.png`` for ``kind`` zeroshot and finetune:
  IQM, mean, median, optimality gap and the probability of improvement with stratified bootstrap
  intervals, and performance profiles (:mod:`dvfb.analysis.aggregate_report`);
* ``budget_zeroshot.md/.csv/.png`` (when some method has zero-shot results at two snapshots or
  more): every snapshot's Table 1, the IQM against the pre-training frames with its intervals, the
  ranking and the probability of improvement at each snapshot (:mod:`dvfb.analysis.budget`);
* with ``paper=True``, ``paper_comparison.md/.csv``: every cell of the paper's results tables, per
  task and per average, beside the report's column of the same method and flags, with how the
  runs behind each column compare with the paper's budget, and a note on the budget of all of them
  (:mod:`dvfb.analysis.paper`, docs/reproduce.md); report.md gets the same section.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dvfb.analysis import aggregate_report
from dvfb.analysis import budget as budget_curves
from dvfb.analysis import paper as paper_tables
from dvfb.analysis.aggregate_report import BootstrapConfig
from dvfb.analysis.common import (
    SUCCESS,
    AnalysisError,
    check_duplicates,
    discover_runs,
    finetune_scores,
    mixed_pretraining_notes,
    random_scores,
    split_budgets,
    zeroshot_scores,
)
from dvfb.analysis.curves import load_curves, load_episode_curves, plot_curves
from dvfb.analysis.normalise import CHOICES, NORMALISERS
from dvfb.analysis.tables import Table, build_table, success_markdown_section, table_markdown_section, to_csv
from dvfb.runs import check_writable

TABLE1 = "Table 1: zero-shot"
TABLE2 = "Table 2: fine-tuning (last evaluation of each curve)"
TABLE6_ZEROSHOT = "Table 6: zero-shot success rate"
TABLE6_FINETUNE = "Table 6: success rate after fine-tuning (last evaluation of each curve)"


@dataclass
class Report:
    out_dir: Path
    zeroshot: Table | None = None
    finetune: Table | None = None
    success_zeroshot: Table | None = None
    success_finetune: Table | None = None
    files: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    aggregates: dict[str, aggregate_report.Aggregates] = field(default_factory=dict)  # kind -> aggregates
    paper: paper_tables.PaperComparison | None = None  # with paper=True (dvfb report --paper)
    budget: budget_curves.Budget | None = None  # zero-shot at several snapshots (dvfb.analysis.budget)


def _outputs(out_dir: Path, has_zeroshot: bool, has_finetune: bool, success: tuple[bool, bool]) -> list[Path]:
    names = ["report.md"]
    if any(success):
        names.append("table6_success.md")
    names += [f"table6_success_{kind}.csv" for kind, has in zip(("zeroshot", "finetune"), success) if has]
    if has_zeroshot:
        names += ["table1_zeroshot.md", "table1_zeroshot.csv", "table1_zeroshot_normalised.csv"]
    if has_finetune:
        names += ["table2_finetune.md", "table2_finetune.csv", "table2_finetune_normalised.csv"]
    return [out_dir / n for n in names]


def make_report(paths: Sequence[str | os.PathLike], out_dir: str | os.PathLike, *, spread: str = "std",
                random_files: Sequence[str | os.PathLike] = (), overwrite: bool = False,
                normaliser: str = "auto", bootstrap: BootstrapConfig | None = None,
                curve_band: str = "ci", paper: bool = False) -> Report:
    """Discover runs under ``paths`` and write the tables, aggregates and curves into ``out_dir``.

    ``paper`` adds ``paper_comparison.md/.csv`` and a section of report.md: the paper's cells, per
    task and per average, beside the report's (:mod:`dvfb.analysis.paper`, docs/reproduce.md).

    ``normaliser`` chooses the scores of the aggregates (docs/reports.md): ``auto`` the first of
    min-max, supervised and expert that covers every task; a named one must cover them (else an
    AnalysisError naming what is missing); ``none`` raw returns.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise AnalysisError(f"--out {out_dir} is a file; give a directory for the report")
    if normaliser not in CHOICES:
        raise AnalysisError(f"--normaliser must be one of {', '.join(CHOICES)}, got {normaliser!r}")
    bootstrap = bootstrap or BootstrapConfig()
    if bootstrap.samples < 100 or not 0 < bootstrap.confidence < 1:
        raise AnalysisError("--bootstrap-samples must be at least 100 and --confidence within (0, 1)")
    runs = discover_runs(paths)
    # Numbers of one method from different pre-training budgets are different columns.
    zs_read, ft_read = zeroshot_scores(runs.pretrain), finetune_scores(runs.finetune)
    zs, ft = split_budgets(zs_read), split_budgets(ft_read)
    rnd = random_scores(random_files)
    check_duplicates([*zs, *ft, *rnd])
    zs_success = split_budgets(zeroshot_scores(runs.pretrain, SUCCESS))
    ft_success = split_budgets(finetune_scores(runs.finetune, SUCCESS))
    budget_notes = mixed_pretraining_notes(zs_read, "Table 1") + mixed_pretraining_notes(ft_read, "Table 2")
    rnd_success = random_scores(random_files, SUCCESS)
    if not zs and not ft:
        found = f"{len(runs.pretrain)} pre-training run(s)" if runs.pretrain else "no dvfb run"
        raise AnalysisError(f"found {found} and no zero-shot or fine-tuning results under "
                            f"{', '.join(map(str, paths))}; run `dvfb zeroshot` or `dvfb finetune` first")
    report = Report(out_dir, notes=budget_notes)
    labels = {score.source: score.method for score in ft}  # a curve's method: its score's column
    curves = load_curves(runs.finetune, labels) if ft else {}
    episodes = load_episode_curves(runs.finetune, labels) if ft else {}
    # Everything is computed before anything is written: a missing reference fails with no file.
    for kind, scores, title in (("zeroshot", [*zs, *rnd], TABLE1), ("finetune", ft, TABLE2)):
        result = aggregate_report.compute(scores, kind, title, normaliser, bootstrap) if scores else None
        if result is not None and result.scopes:
            report.aggregates[kind] = result
    planned = _outputs(out_dir, bool(zs or rnd), bool(ft), (bool(zs_success or rnd_success), bool(ft_success)))
    final = report.aggregates.get("zeroshot")
    report.budget = budget_curves.compute(budget_curves.snapshot_scores(runs.pretrain), rnd,
                                          {scope.name: scope.normaliser for scope in final.scopes}
                                          if final is not None else {}, spread, bootstrap)
    if report.budget is not None:
        planned += [out_dir / f"budget_zeroshot.{suffix}" for suffix in ("md", "csv", "png")]
    published = None
    if paper:  # the package's tables are read (and checked) before anything is written
        published = (paper_tables.load_paper_tables(), paper_tables.run_budget(runs, zs, ft),
                     paper_tables.method_budgets(runs, [*zs, *zs_success], [*ft, *ft_success]))
        planned += [out_dir / "paper_comparison.md", out_dir / "paper_comparison.csv"]
    planned += [out_dir / "curves" / f"finetune_{task}.png" for task in curves]
    planned += [out_dir / "curves" / f"episodes_{task}.png" for task in episodes]
    for kind in report.aggregates:
        planned += [out_dir / f"aggregates_{kind}.md", out_dir / f"aggregates_{kind}.csv", out_dir / f"profiles_{kind}.png"]
    planned += [out_dir / f"{stem}_{name}.csv" for stem in ("table1_zeroshot", "table2_finetune")
                for name in NORMALISERS[1:]]
    existing = [p for p in planned if p.exists()]
    if existing and not overwrite:
        raise AnalysisError(f"{existing[0]} exists; pass --overwrite to replace the report in {out_dir}")
    check_writable(out_dir)  # a read-only or full disk: one line, before the first file
    try:
        return _write_report(report, paths, out_dir, spread, zs, ft, rnd, zs_success, ft_success, rnd_success,
                             runs, curves, bootstrap, curve_band, published, episodes)
    except OSError as exc:
        raise AnalysisError(f"cannot write the report in {out_dir}: {exc.strerror or exc}") from exc


def _write_report(report, paths, out_dir, spread, zs, ft, rnd, zs_success, ft_success, rnd_success, runs, curves,
                  bootstrap, curve_band, paper=None, episodes=None) -> Report:

    sections = ["# dvfb report", "", "Runs: " + ", ".join(f"`{p}`" for p in paths) + ".", ""]
    if zs or rnd:
        # The random column only makes sense next to the zero-shot table (the floor of Table 1).
        report.zeroshot = build_table([*zs, *rnd], TABLE1, spread)
        section = table_markdown_section(report.zeroshot)
        _write(out_dir / "table1_zeroshot.md", section + "\n", report)
        _write(out_dir / "table1_zeroshot.csv", to_csv(report.zeroshot), report)
        _write(out_dir / "table1_zeroshot_normalised.csv", to_csv(report.zeroshot, normalised=True), report)
        _write_normalised(out_dir, "table1_zeroshot", report.zeroshot, report)
        sections += [section, ""]
    if ft:
        report.finetune = build_table(ft, TABLE2, spread)
        section = table_markdown_section(report.finetune)
        frames = Counter(s.frames for s in ft)
        if len(frames) > 1:
            report.notes.append("fine-tuning runs end at different frame counts: " + ", ".join(
                f"{n} run(s) at {f}" for f, n in sorted(frames.items())) + "; Table 2 mixes budgets")
        unfinished = [str(r.path) for r in runs.finetune if not r.run.is_finished()]
        if unfinished:
            report.notes.append("unfinished fine-tuning runs (last evaluation used): " + ", ".join(unfinished))
        frames_text = ", ".join(str(f) for f in sorted(frames))
        section = section.replace("Episode return:", f"Fine-tuning frames at the last point: {frames_text}. "
                                  "Episode return:", 1)
        _write(out_dir / "table2_finetune.md", section + "\n", report)
        _write(out_dir / "table2_finetune.csv", to_csv(report.finetune), report)
        _write(out_dir / "table2_finetune_normalised.csv", to_csv(report.finetune, normalised=True), report)
        _write_normalised(out_dir, "table2_finetune", report.finetune, report)
        sections += [section, ""]
        pngs = plot_curves(curves, out_dir / "curves", curve_band, bootstrap.seed)
        report.files += pngs
        sections += ["## Fine-tuning curves", ""]
        sections += [f"![{p.stem}](curves/{p.name})" for p in pngs]
        sections.append("")
        if episodes:  # test-time search and online task inference: their claim is per episode
            pngs = plot_curves(episodes, out_dir / "curves", curve_band, bootstrap.seed, kind="episodes")
            report.files += pngs
            sections += ["## Returns of the episodes of interaction", "",
                         "The return of every training episode of the protocols that record them (test-time "
                         "search over z, online task inference), against the episodes of interaction, with "
                         "the fine-tuning curves' intervals.", ""]
            sections += [f"![{p.stem}](curves/{p.name})" for p in pngs]
            sections.append("")
    for kind, result in report.aggregates.items():
        figure = aggregate_report.plot_profiles(result, out_dir / f"profiles_{kind}.png", bootstrap.confidence)
        report.files.append(figure)
        section = aggregate_report.markdown(result, bootstrap, figure.name)
        _write(out_dir / f"aggregates_{kind}.md", section + "\n", report)
        _write(out_dir / f"aggregates_{kind}.csv", aggregate_report.to_csv(result), report)
        report.notes += result.notes
        sections += [section, ""]
    if report.budget is not None:
        figure = budget_curves.plot(report.budget, out_dir / "budget_zeroshot.png", bootstrap.confidence)
        report.files.append(figure)
        section = budget_curves.markdown(report.budget, bootstrap, figure.name)
        _write(out_dir / "budget_zeroshot.md", section + "\n", report)
        _write(out_dir / "budget_zeroshot.csv", budget_curves.to_csv(report.budget), report)
        report.notes += report.budget.notes
        sections += [section, ""]
    success_sections = []
    if zs_success or rnd_success:
        report.success_zeroshot = build_table([*zs_success, *rnd_success], TABLE6_ZEROSHOT, spread, digits=2)
        success_sections.append(success_markdown_section(report.success_zeroshot))
        _write(out_dir / "table6_success_zeroshot.csv", to_csv(report.success_zeroshot), report)
    if ft_success:
        report.success_finetune = build_table(ft_success, TABLE6_FINETUNE, spread, digits=2)
        success_sections.append(success_markdown_section(report.success_finetune))
        _write(out_dir / "table6_success_finetune.csv", to_csv(report.success_finetune), report)
    if success_sections:
        _write(out_dir / "table6_success.md", "\n\n".join(success_sections) + "\n", report)
        sections += ["\n\n".join(success_sections), ""]
    if paper is not None:
        published, budget, budgets = paper
        report.paper = paper_tables.compare(report.zeroshot, report.finetune, budget,
                                            success_zeroshot=report.success_zeroshot,
                                            success_finetune=report.success_finetune, budgets=budgets,
                                            tables=published)
        section = paper_tables.to_markdown(report.paper)
        _write(out_dir / "paper_comparison.md", section + "\n", report)
        _write(out_dir / "paper_comparison.csv", paper_tables.to_csv(report.paper), report)
        sections += [section, ""]
    if report.notes:
        sections += ["## Notes", ""] + [f"- {note}" for note in report.notes] + [""]
    _write(out_dir / "report.md", "\n".join(sections), report)
    return report


def _write_normalised(out_dir: Path, stem: str, table, report: Report) -> None:
    for name in NORMALISERS[1:]:
        if table.normalised_by.get(name):
            _write(out_dir / f"{stem}_{name}.csv", to_csv(table, normalised=name), report)


def _write(path: Path, text: str, report: Report) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    report.files.append(path)
