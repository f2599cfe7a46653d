"""``dvfb report``: the paper's tables and the fine-tuning curves from run directories."""

from __future__ import annotations

import argparse

from dvfb.analysis import aggregate_report, budget
from dvfb.analysis.aggregate import BOOTSTRAP_SAMPLES, CONFIDENCE
from dvfb.analysis.aggregate_report import BootstrapConfig
from dvfb.analysis.normalise import CHOICES
from dvfb.analysis.paper import to_markdown as paper_markdown
from dvfb.analysis.report import make_report
from dvfb.analysis.tables import to_markdown
from dvfb.cli.common import Formatter, integer, seed_value


def cmd_report(args: argparse.Namespace) -> int:
    """Tables 1, 2 and 6 of the paper and fine-tuning curves from run directories."""
    bootstrap = BootstrapConfig(args.bootstrap_samples, args.confidence, args.bootstrap_seed)
    report = make_report(args.runs, args.out, spread="se" if args.stderr else "std",
                         random_files=args.random or (), overwrite=args.overwrite, normaliser=args.normaliser,
                         bootstrap=bootstrap, curve_band=args.curve_band, paper=args.paper)
    if not args.aggregates_only:
        for table in (report.zeroshot, report.finetune, report.success_zeroshot, report.success_finetune):
            if table is not None:
                print(f"## {table.title}\n\n{to_markdown(table)}\n")
                for name in ("supervised", "minmax"):
                    if table.normalised_by.get(name):
                        print(f"### {table.title}: {name}-normalised\n\n{to_markdown(table, normalised=name)}\n")
    for result in report.aggregates.values():
        print(aggregate_report.markdown(result, bootstrap, None, heading_level=2))
    if report.budget is not None:
        print(budget.markdown(report.budget, bootstrap, None, heading_level=2))
    if report.paper is not None:
        print(paper_markdown(report.paper) + "\n")
    for note in report.notes:
        print(f"note: {note}")
    print(f"report written to {report.out_dir} ({len(report.files)} files; see {report.out_dir / 'report.md'})")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "report", help="Tables 1, 2 and 6, normalised scores, aggregates with bootstrap intervals, profiles and curves",
        formatter_class=Formatter,
        description="Markdown and CSV tables shaped like the paper's Table 1 (zero-shot) and Table 2 "
                    "(fine-tuning, last point of each curve): rows domain/task with per-domain averages, "
                    "columns methods (from the run configs: dvfb, dvfb_wo_ce, fb, ..._wo_svf, ..._wo_map), "
                    "mean ± std over seeds (ddof=1), plus normalised scores (URLB expert; the supervised reference "
                    "of `dvfb supervised`; min-max between random and supervised), aggregates over runs x tasks "
                    "(IQM, mean, median, optimality gap, probability of improvement) with stratified bootstrap "
                    "intervals and performance profiles (docs/reports.md). Missing results are gaps. Figures "
                    "are written as PNG.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories or directories containing runs")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--stderr", action="store_true", help="show the standard error over seeds instead of the std")
    p.add_argument("--random", nargs="+", action="extend", default=None, metavar="FILE.json",
                   help="random-policy files (dvfb random-policy --output) for a 'random' column; "
                        "give it after the run directories, or repeat it")
    p.add_argument("--overwrite", action="store_true", help="replace existing report files in --out")
    p.add_argument("--normaliser", default="auto", choices=CHOICES,
                   help="scores of the aggregates: min-max (random 0, supervised 100), percent of the supervised "
                        "reference, percent of the URLB expert, or raw returns; auto: the first of minmax, "
                        "supervised, expert that covers every task (default: %(default)s)")
    p.add_argument("--bootstrap-samples", type=integer(1), default=BOOTSTRAP_SAMPLES,
                   help="resamples of the stratified bootstrap (default: %(default)s)")
    p.add_argument("--bootstrap-seed", type=seed_value, default=0, help="seed of the bootstrap (default: %(default)s)")
    p.add_argument("--confidence", type=float, default=CONFIDENCE, help="level of the intervals (default: %(default)s)")
    p.add_argument("--curve-band", default="ci", choices=("ci", "std", "se"),
                   help="band of the fine-tuning curves: bootstrap interval of the mean (3+ seeds), ± std or "
                        "± standard error (default: %(default)s)")
    p.add_argument("--paper", action="store_true",
                   help="also write paper_comparison.md/.csv and a section of report.md: every cell of the "
                        "paper's Tables 1, 2 and 5-12, per task and per average, beside the report's column of the "
                        "same method and flags (mean ± std, seeds), the difference, how the runs behind each column "
                        "compare with the paper's budget (frames, preset), and the sweep files that run what is "
                        "missing (docs/reproduce.md)")
    p.add_argument("--aggregates-only", action="store_true",
                   help="print only the aggregates (every file is still written)")
    p.set_defaults(func=cmd_report)
