"""The paper's published numbers, and a report's domain averages set beside them
(``dvfb report --paper``; docs/reproduce.md, docs/reports.md).

The numbers ship with the package as CSV files in ``dvfb/data/paper_tables/`` (read through
:mod:`importlib.resources`), one row per published number::

    table,kind,domain,method,paper_name,value,source
    1,zeroshot,walker,fb,FB,114,paper Table 1 (zero-shot); domain average

* ``table``: the paper's table (1: zero-shot, 2: after 100k fine-tuning frames, 8: DVFB's intrinsic
  reward swapped for another, zero-shot on walker);
* ``kind``: the report table it is compared with, ``zeroshot`` (Table 1) or ``finetune`` (Table 2,
  the last evaluation of each fine-tuning curve);
* ``method``: the report's column name (:func:`dvfb.analysis.common.method_name`): an agent's name
  (``fb``, ``cic``, ...), the successor-feature variants ``SF-Lap``, ``SF-LRA-P``, ``SF-LRA-SR``,
  ``SF-CL`` (``--agent sf --sf.features ...``; the paper calls them Lap, LRA-P, LRA-SR, CL) and the
  Table 8 variants ``dvfb_icm_apt``, ``dvfb_proto``, ``dvfb_cic`` (``--exploration.reward ...``);
  ``paper_name`` is the paper's column header;
* ``value``: the domain average of the episode return, the mean over the domain's tasks
  (docs/tasks.md) of the mean over seeds, which is how the report's ``average`` rows are built
  (:mod:`dvfb.analysis.tables`).

A comparison row is ``compared`` (the report has the method's domain average), ``incomplete`` (the
report has some of the domain's tasks, so no average) or ``not run``. The notes say how far the
runs' budget (pre-training frames, preset, fine-tuning frames) is from the paper's: 2M pre-training
frames, the paper's network sizes and 100k fine-tuning frames (docs/reproduce.md).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import resources

from dvfb.analysis.common import AnalysisError, Runs, Score, split_budget_label
from dvfb.analysis.tables import AVERAGE, Table

PAPER_PRETRAIN_FRAMES = 2_000_000
PAPER_FINETUNE_FRAMES = 100_000
# Presets with the paper's network sizes and batch (docs/methods.md, "Hyper-parameters").
FULL_SIZE_PRESETS = ("paper", "code", "fbee")
KINDS = ("zeroshot", "finetune")
FIELDS = ("table", "kind", "domain", "method", "paper_name", "value", "source")
CSV_FIELDS = ("table", "kind", "domain", "method", "paper_name", "report_value", "report_seeds", "paper_value",
              "difference", "status", "source")
DATA_PACKAGE = "dvfb"
DATA_DIR = ("data", "paper_tables")

COMPARED = "compared"
NOT_RUN = "not run"
INCOMPLETE = "incomplete"


@dataclass(frozen=True)
class PaperNumber:
    """One published number: a method's domain average in one of the paper's tables."""

    table: int
    kind: str
    domain: str
    method: str
    paper_name: str
    value: float
    source: str


def parse_paper_csv(text: str, name: str) -> list[PaperNumber]:
    """The rows of one paper-table CSV; a malformed file is an :class:`AnalysisError` naming the line."""
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != FIELDS:
        raise AnalysisError(f"paper table {name}: expected the columns {','.join(FIELDS)}, "
                            f"got {','.join(reader.fieldnames or ()) or 'none'}")
    numbers = []
    for line, row in enumerate(reader, start=2):
        if None in row or any(row[k] is None or not row[k].strip() for k in FIELDS):
            raise AnalysisError(f"paper table {name} line {line}: every one of {','.join(FIELDS)} needs a value")
        if row["kind"] not in KINDS:
            raise AnalysisError(f"paper table {name} line {line}: kind must be one of {', '.join(KINDS)}, "
                                f"got {row['kind']!r}")
        try:
            table, value = int(row["table"]), float(row["value"])
        except ValueError:
            raise AnalysisError(f"paper table {name} line {line}: table must be an integer and value a number") \
                from None
        if not math.isfinite(value):
            raise AnalysisError(f"paper table {name} line {line}: value {row['value']!r} is not finite")
        numbers.append(PaperNumber(table, row["kind"], row["domain"], row["method"], row["paper_name"], value,
                                   row["source"]))
    return numbers


def load_paper_numbers() -> list[PaperNumber]:
    """Every published number of the CSVs shipped in ``dvfb/data/paper_tables/``, in file order.

    Two rows for the same (table, domain, method) are an error.
    """
    folder = resources.files(DATA_PACKAGE).joinpath(*DATA_DIR)
    try:
        files = sorted((entry for entry in folder.iterdir() if entry.name.endswith(".csv")), key=lambda e: e.name)
        numbers = [n for entry in files for n in parse_paper_csv(entry.read_text(encoding="utf-8"), entry.name)]
    except OSError as exc:
        raise AnalysisError(f"the paper's tables cannot be read from the dvfb package: {exc}") from exc
    if not numbers:
        raise AnalysisError("the dvfb package holds no paper tables (data/paper_tables/*.csv); reinstall dvfb")
    seen: set[tuple[int, str, str]] = set()
    for number in numbers:
        key = (number.table, number.domain, number.method)
        if key in seen:
            raise AnalysisError(f"the paper tables list Table {number.table}, {number.domain}, {number.method} twice")
        seen.add(key)
    return numbers


# ---------------------------------------------------------------------------------------------
# the runs' budget


@dataclass(frozen=True)
class Budget:
    """What the report's numbers were trained with: presets, pre-training frames behind the
    zero-shot and fine-tuning numbers, and fine-tuning frames at the last curve point."""

    presets: tuple[str, ...] = ()
    pretrain_frames: tuple[int, ...] = ()
    finetune_frames: tuple[int, ...] = ()


def run_budget(runs: Runs, zeroshot: Iterable[Score], finetune: Iterable[Score]) -> Budget:
    """The budget of a report's runs, from their configs and scores."""
    presets = {str(r.config.preset) for r in runs.pretrain}
    presets |= {str(r.parent.config.preset) for r in runs.finetune if r.parent is not None}
    pretrain = set()
    for score in zeroshot:
        if score.pretrain_frames:
            pretrain.add(int(score.pretrain_frames))
    parents = {str(r.path): r.parent for r in runs.finetune}
    finetune_frames = set()
    for score in finetune:
        if score.frames is not None:
            finetune_frames.add(int(score.frames))
        parent = parents.get(str(score.source.parent))
        if score.pretrain_frames:  # fine-tuned from a named snapshot
            pretrain.add(int(score.pretrain_frames))
        elif parent is not None:  # from the final snapshot of its pre-training run
            pretrain.add(int(parent.config.frames))
    if not pretrain:
        pretrain = {int(r.config.frames) for r in runs.pretrain}
    return Budget(tuple(sorted(presets)), tuple(sorted(pretrain)), tuple(sorted(finetune_frames)))


def _frames(values: Sequence[int]) -> str:
    return ", ".join(f"{v:,}" for v in values)


def scale_notes(budget: Budget, has_finetune: bool) -> list[str]:
    """How the runs' budget compares with the paper's; the first note says whether the comparison
    is at the paper's scale at all."""
    below = []
    small_pretrain = [f for f in budget.pretrain_frames if f < PAPER_PRETRAIN_FRAMES]
    if small_pretrain:
        share = 100 * max(small_pretrain) / PAPER_PRETRAIN_FRAMES
        below.append(f"pre-training of {_frames(small_pretrain)} frames (the paper: {PAPER_PRETRAIN_FRAMES:,}; "
                     f"{share:.2g}% of it at most)")
    reduced = [p for p in budget.presets if p not in FULL_SIZE_PRESETS]
    if reduced:
        below.append(f"preset {', '.join(reduced)} (narrower networks and smaller batches than the paper's; "
                     "presets paper and code have its sizes, docs/methods.md 'Hyper-parameters')")
    short = [f for f in budget.finetune_frames if f < PAPER_FINETUNE_FRAMES]
    if has_finetune and short:
        below.append(f"fine-tuning curves ending at {_frames(short)} frames (the paper's Table 2: "
                     f"{PAPER_FINETUNE_FRAMES:,})")
    if below:
        first = ("**Scale: these runs are far below the paper's budget**, so the differences below measure the "
                 "budget at least as much as the implementation: " + "; ".join(below) + ". Compare at the paper's "
                 "scale with the sweeps of docs/reproduce.md.")
    else:
        first = (f"Scale: the runs match the paper's budget ({PAPER_PRETRAIN_FRAMES:,} pre-training frames, preset "
                 f"{', '.join(budget.presets) or 'unknown'}"
                 + (f", {PAPER_FINETUNE_FRAMES:,} fine-tuning frames" if has_finetune else "") + "). Differences "
                 "that remain include dvfb's documented decisions (docs/methods.md §11, docs/reproduce.md "
                 "'Known deviations') and the physics versions (docs/tasks.md §7).")
    return [first]


# ---------------------------------------------------------------------------------------------
# the comparison


@dataclass(frozen=True)
class ComparisonRow:
    number: PaperNumber
    status: str  # compared, not run, or incomplete
    report_value: float | None = None
    seeds: int | None = None
    detail: str = ""  # for incomplete: the tasks the report has
    column: str = ""  # the report's column, where it is not the method's name: one of its budgets

    @property
    def method(self) -> str:
        return self.column or self.number.method

    @property
    def difference(self) -> float | None:
        return None if self.report_value is None else self.report_value - self.number.value


@dataclass
class PaperComparison:
    rows: list[ComparisonRow]
    budget: Budget
    notes: list[str] = field(default_factory=list)

    @property
    def compared(self) -> list[ComparisonRow]:
        return [r for r in self.rows if r.status == COMPARED]


def _rows(number: PaperNumber, table: Table | None) -> list[ComparisonRow]:
    """The published number beside the report's column of its method, or beside each of the
    columns of the method's pre-training budgets where the report keeps them apart."""
    if table is None:
        return [ComparisonRow(number, NOT_RUN)]
    budgets = [c for c in table.columns if split_budget_label(c)[0] == number.method and c != number.method]
    rows = [_row(number, table, column) for column in [number.method, *budgets]]
    found = [row for row in rows if row.status != NOT_RUN]
    return found or rows[:1]


def _row(number: PaperNumber, table: Table, column: str) -> ComparisonRow:
    name = "" if column == number.method else column
    cell = table.cell(number.domain, AVERAGE, column)
    if cell is not None:
        return ComparisonRow(number, COMPARED, cell.mean, cell.n, column=name)
    tasks = [task for domain, task in table.rows if domain == number.domain and task != AVERAGE]
    have = [task for task in tasks if table.cell(number.domain, task, column) is not None]
    if have:
        return ComparisonRow(number, INCOMPLETE, detail=f"{len(have)} of {len(tasks)} tasks", column=name)
    return ComparisonRow(number, NOT_RUN, column=name)


def compare(zeroshot: Table | None, finetune: Table | None, budget: Budget,
            numbers: Sequence[PaperNumber] | None = None) -> PaperComparison:
    """Every published number beside the report's domain average of the same method (raw returns).

    ``zeroshot`` and ``finetune`` are the report's Table 1 and Table 2 (None: not in the report).
    """
    numbers = load_paper_numbers() if numbers is None else list(numbers)
    tables = {"zeroshot": zeroshot, "finetune": finetune}
    rows = [row for number in numbers for row in _rows(number, tables[number.kind])]
    comparison = PaperComparison(rows, budget, scale_notes(budget, finetune is not None))
    published = {(n.kind, n.method) for n in numbers}
    for kind, table in tables.items():
        if table is None:
            continue
        extra = [m for m in table.columns if m != "random" and (kind, split_budget_label(m)[0]) not in published]
        if extra:
            comparison.notes.append(f"no published {kind} number for {', '.join(extra)} (the paper tables dvfb "
                                    "ships: docs/reproduce.md)")
    missing = sorted({r.number.method for r in rows if r.status == NOT_RUN})
    if missing:
        comparison.notes.append(f"{sum(r.status == NOT_RUN for r in rows)} published number(s) have no run here "
                                f"('not run'), of the methods {', '.join(missing)}")
    if any(r.status == INCOMPLETE for r in rows):
        comparison.notes.append("'incomplete': the report lacks some of the domain's tasks for that method, so it "
                                "has no domain average (docs/tasks.md lists the tasks)")
    return comparison


def _number_text(value: float | None, signed: bool = False) -> str:
    if value is None:
        return "–"
    return f"{value:+.1f}" if signed else f"{value:.1f}"


def to_markdown(comparison: PaperComparison, heading_level: int = 2) -> str:
    """The comparison as a markdown section: the scale note first, then one row per published number."""
    hashes = "#" * heading_level
    lines = [f"{hashes} Comparison with the paper's numbers", "", comparison.notes[0], "",
             "Domain averages of the episode return: the report's `average` rows (mean over the domain's tasks "
             "of the mean over seeds) and the paper's published averages (its Tables 1, 2 and 8). "
             "Difference: this report minus the paper.", "",
             "| table | domain | method | paper's name | this report | seeds | paper | difference | status |",
             "|---:|---|---|---|---:|---:|---:|---:|---|"]
    for row in comparison.rows:
        n = row.number
        status = row.status + (f" ({row.detail})" if row.detail else "")
        lines.append(f"| {n.table} | {n.domain} | {row.method} | {n.paper_name} | {_number_text(row.report_value)} | "
                     f"{'–' if row.seeds is None else row.seeds} | {n.value:g} | "
                     f"{_number_text(row.difference, signed=True)} | {status} |")
    if len(comparison.notes) > 1:
        lines += [""] + [f"- {note}" for note in comparison.notes[1:]]
    return "\n".join(lines)


def to_csv(comparison: PaperComparison) -> str:
    """One line per published number (:data:`CSV_FIELDS`); the report's value and the difference are
    empty where the report has none."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_FIELDS)
    for row in comparison.rows:
        n = row.number
        status = row.status + (f" ({row.detail})" if row.detail else "")
        writer.writerow([n.table, n.kind, n.domain, row.method, n.paper_name,
                         "" if row.report_value is None else repr(row.report_value),
                         "" if row.seeds is None else row.seeds, repr(n.value),
                         "" if row.difference is None else repr(row.difference), status, n.source])
    return out.getvalue()
