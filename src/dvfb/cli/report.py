"""``dvfb report``: the paper's tables and the fine-tuning curves from run directories."""

from __future__ import annotations

import argparse

from dvfb.cli.common import Formatter

def cmd_report(args: argparse.Namespace) -> int:
    """Tables 1, 2 and 6 of the paper and fine-tuning curves from run directories."""
    from dvfb.analysis.report import make_report
    from dvfb.analysis.tables import to_markdown

    report = make_report(args.runs, args.out, spread="se" if args.stderr else "std",
                         random_files=args.random or (), overwrite=args.overwrite)
    for table in (report.zeroshot, report.finetune, report.success_zeroshot, report.success_finetune):
        if table is not None:
            print(f"## {table.title}\n\n{to_markdown(table)}\n")
    for note in report.notes:
        print(f"note: {note}")
    print(f"report written to {report.out_dir} ({len(report.files)} files; see {report.out_dir / 'report.md'})")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "report", help="Table 1 (zero-shot), Table 2 (fine-tuning), Table 6 (success rates) and fine-tuning curves",
        formatter_class=Formatter,
        description="Markdown and CSV tables shaped like the paper's Table 1 (zero-shot) and Table 2 "
                    "(fine-tuning, last point of each curve): rows domain/task with per-domain averages, "
                    "columns methods (from the run configs: dvfb, dvfb_wo_ce, fb, ..._wo_svf, ..._wo_map), "
                    "mean ± std over seeds (ddof=1), plus expert-normalised scores (URLB expert returns, "
                    "walker and quadruped). Missing results are gaps. Fine-tuning curves are written as PNG.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories or directories containing runs")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--stderr", action="store_true", help="show the standard error over seeds instead of the std")
    p.add_argument("--random", nargs="+", action="extend", default=None, metavar="FILE.json",
                   help="random-policy files (dvfb random-policy --output) for a 'random' column; "
                        "give it after the run directories, or repeat it")
    p.add_argument("--overwrite", action="store_true", help="replace existing report files in --out")
    p.set_defaults(func=cmd_report)
