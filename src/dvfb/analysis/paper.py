"""The paper's published numbers, every cell of its results tables, set beside a report's
(``dvfb report --paper``; docs/reproduce.md, docs/reports.md).

Two CSV files ship with the package in ``dvfb/data/paper_tables/`` (read through
:mod:`importlib.resources`):

* ``cells.csv``, one row per number of the paper's Tables 1, 2 and 5-12::

      table,kind,domain,task,paper_name,mean,std,seeds,note
      1,zero_shot,walker,stand,FB,303,55,6,

  ``kind`` is the kind of the paper's table (``zero_shot``, ``fine_tune``,
  ``zero_shot_offline_comparison``, ``zero_shot_extra_domains``, ``ablation_zero_shot``,
  ``ablation_fine_tune``); ``task`` the paper's task (dvfb's task is ``<domain>_<task>``), or
  ``average`` (a domain's average; in Table 5 also over all domains, domain ``all``) or
  ``average_of_best`` (Table 5's last row); ``paper_name`` the paper's column; ``std`` and
  ``seeds`` are empty where the paper gives none. Meta-World cells are success rates (0 to 1),
  the others episode returns. ``note`` says what the transcription noticed: the averages the paper
  prints inconsistently keep their printed value, and the note says so.
* ``methods.csv``, one row per column of the paper (``table``, ``paper_name``): how dvfb makes that
  column::

      table,paper_name,agent,flags,method,sweep,note
      10,α=3,dvfb,--exploration.alpha 3,dvfb_alpha3,table10_alpha.toml,...

  ``agent`` and ``flags`` are ``dvfb pretrain`` options (``{domain}`` stands for the cell's domain,
  in a dataset's directory); ``method`` is the report's column of such a run at preset ``paper``
  (:func:`dvfb.analysis.common.method_name`); ``sweep`` names the files of ``sweeps/paper/`` that
  run it. An empty ``agent`` marks a row with no single dvfb column (Table 5's "Average of best").

A cell is compared with the report column that a run of its agent and flags gets under the preset
of the report's runs (so Table 10's "α = 5" is the column ``dvfb`` of runs at preset ``paper`` and
``dvfb_alpha5`` at preset ``code``, whose alpha is 50): per task, the column's mean ± std over seeds;
per average, the column's ``average`` row (:mod:`dvfb.analysis.tables`). Every comparison row says
how the runs behind the column compare with the paper's budget (pre-training frames, preset,
fine-tuning frames): :func:`scale_marker`.

:func:`compare_table` compares one report table (returns or success rates, zero-shot or
fine-tuning) with the paper's cells of its kind; it is what the rest of the report calls, and
:func:`cells_markdown` draws its rows. :func:`compare` does it for a whole report.
"""

from __future__ import annotations

import csv
import functools
import io
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources

from dvfb.agents import AGENTS
from dvfb.analysis.common import RETURN, SUCCESS, AnalysisError, Runs, Score, method_name, split_budget_label
from dvfb.analysis.tables import AVERAGE, Summary, Table
from dvfb.core.config import canonical_key, field_type, merge, parse_text
from dvfb.core.errors import DvfbError
from dvfb.runs.presets import preset_config

PAPER_PRETRAIN_FRAMES = 2_000_000
PAPER_FINETUNE_FRAMES = 100_000
# Presets with the paper's network sizes and batch (docs/methods.md, "Hyper-parameters").
FULL_SIZE_PRESETS = ("paper", "code", "fbee")
KINDS = ("zeroshot", "finetune")
PAPER_KINDS = ("zero_shot", "fine_tune", "zero_shot_offline_comparison", "zero_shot_extra_domains",
               "ablation_zero_shot", "ablation_fine_tune")
FINE_TUNE_KINDS = ("fine_tune", "ablation_fine_tune")
SUCCESS_DOMAINS = ("metaworld",)  # its cells are success rates (docs/tasks.md §4.6)
ALL_DOMAINS = "all"
AVERAGE_OF_BEST = "average_of_best"
CELL_FIELDS = ("table", "kind", "domain", "task", "paper_name", "mean", "std", "seeds", "note")
METHOD_FIELDS = ("table", "paper_name", "agent", "flags", "method", "sweep", "note")
CSV_FIELDS = ("table", "kind", "domain", "task", "paper_name", "method", "report_value", "report_std",
              "report_seeds", "paper_value", "paper_std", "paper_seeds", "difference", "status", "runs_vs_paper",
              "note")
DATA_PACKAGE = "dvfb"
DATA_DIR = ("data", "paper_tables")
CELLS_FILE = "cells.csv"
METHODS_FILE = "methods.csv"

COMPARED = "compared"
NOT_RUN = "not run"
INCOMPLETE = "incomplete"
PAPER_ONLY = "paper only"  # no single dvfb column (Table 5's "Average of best" of a family)
PAPER_SCALE = "paper scale"

# What each table is, and the budget the paper states for it (its captions, text and Table 4).
TABLE_TITLES = {
    1: "zero-shot", 2: "fine-tuning (100k frames)", 5: "zero-shot, offline methods on exploration datasets",
    6: "zero-shot, point-mass maze and Meta-World", 7: "contrastive-entropy weight β, zero-shot",
    8: "intrinsic rewards, zero-shot", 9: "fine-tuning approaches", 10: "exploration-value weight α, zero-shot",
    11: "contrastive-entropy weight β, zero-shot", 12: "fine-tuning weight η"}
PAPER_BUDGETS = {
    1: "2M reward-free pre-training frames, 10,000 labelled steps to infer the skill, 6 seeds",
    2: "2M pre-training frames, then 100,000 fine-tuning frames; the number of seeds is not stated",
    5: "the starred columns are quoted from Touati et al. (2023), offline on ExORL's datasets, without std; "
       "DVFB is online (2M frames), its walker and quadruped cells are Table 1's",
    6: "2M pre-training frames, 3 seeds on the maze; the offline columns are quoted from MCFB (Jeen et al., "
       "2024); Meta-World: success rates, seeds not stated",
    7: "2M pre-training frames, 3 seeds", 8: "2M pre-training frames, 3 seeds",
    9: "2M pre-training frames, then 100,000 fine-tuning frames, 3 seeds", 10: "2M pre-training frames, 3 seeds",
    11: "2M pre-training frames, 3 seeds", 12: "2M pre-training frames, then 100,000 fine-tuning frames, 3 seeds"}


# ---------------------------------------------------------------------------------------------
# the package data


@dataclass(frozen=True)
class PaperCell:
    """One number of the paper's results tables."""

    table: int
    kind: str  # the paper's kind of table (PAPER_KINDS)
    domain: str
    task: str  # the paper's task, "average" or "average_of_best"
    paper_name: str
    mean: float
    std: float | None
    seeds: int | None
    note: str = ""

    @property
    def report_kind(self) -> str:
        """The report table it is compared with: ``zeroshot`` or ``finetune`` (the last point of each curve)."""
        return "finetune" if self.kind in FINE_TUNE_KINDS else "zeroshot"

    @property
    def metric(self) -> str:
        return SUCCESS if self.domain in SUCCESS_DOMAINS else RETURN

    @property
    def is_average(self) -> bool:
        return self.task in (AVERAGE, AVERAGE_OF_BEST)

    @property
    def report_task(self) -> str:
        """The report's row: dvfb's task name, or ``average``."""
        return AVERAGE if self.is_average else f"{self.domain}_{self.task}"


@dataclass(frozen=True)
class PaperMethod:
    """How dvfb makes one column of one of the paper's tables."""

    table: int
    paper_name: str
    agent: str  # "" where no single dvfb column stands for it
    flags: tuple[str, ...]  # dvfb pretrain options, as typed; "{domain}" is the cell's domain
    method: str  # the report's column at preset paper ("{domain}" as in flags)
    sweeps: tuple[str, ...]  # files of sweeps/paper/ that run it
    note: str = ""

    def overrides(self, domain: str) -> dict:
        """The flags as a nested override dict of the run config (values typed as the flags parse them)."""
        cls = type(preset_config("paper", self.agent))
        nested: dict = {}
        for flag, text in zip(self.flags[::2], self.flags[1::2]):
            key = canonical_key(flag)
            tp = field_type(cls, key)
            if tp is None:
                raise AnalysisError(f"paper table {METHODS_FILE}: Table {self.table} {self.paper_name}: {flag} is not "
                                    f"an option of dvfb pretrain --agent {self.agent}")
            *sections, name = key.split(".")
            target = nested
            for section in sections:
                target = target.setdefault(section, {})
            target[name] = parse_text(key, tp, text.replace("{domain}", domain))
        return nested

    def label(self, preset: str, domain: str, kind: str) -> str | None:
        """The report's column of a run of these flags under ``preset`` (None: no dvfb column, or the
        flags do not make a valid config of that preset)."""
        return _label(self, preset, domain, kind)


@functools.lru_cache(maxsize=None)
def _label(method: PaperMethod, preset: str, domain: str, kind: str) -> str | None:
    if not method.agent:
        return None
    try:
        config = merge(preset_config(preset, method.agent), method.overrides(domain))
    except DvfbError:
        return None
    return method_name(config, config.finetune if kind == "finetune" else None)


def _rows(text: str, name: str, fields: tuple[str, ...]) -> Iterator[tuple[str, dict[str, str]]]:
    """``(where, row)`` for each row of a CSV with exactly ``fields`` as its columns and a value (maybe
    empty) in each; ``where`` names the file and line for errors."""
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != fields:
        raise AnalysisError(f"paper table {name}: expected the columns {','.join(fields)}, "
                            f"got {','.join(reader.fieldnames or ()) or 'none'}")
    for line, row in enumerate(reader, start=2):
        where = f"paper table {name} line {line}"
        if None in row or any(row[k] is None for k in fields):
            raise AnalysisError(f"{where}: expected {len(fields)} values")
        yield where, row


def _number(text: str, what: str, where: str, integer: bool = False) -> float | int | None:
    if not text.strip():
        return None
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        raise AnalysisError(f"{where}: {what} {text!r} is not {'an integer' if integer else 'a number'}") from None
    if not math.isfinite(value):
        raise AnalysisError(f"{where}: {what} {text!r} is not finite")
    return value


def parse_cells(text: str, name: str = CELLS_FILE) -> list[PaperCell]:
    """The rows of ``cells.csv``; a malformed row is an :class:`AnalysisError` naming the line."""
    cells = []
    for where, row in _rows(text, name, CELL_FIELDS):
        required = ("table", "kind", "domain", "task", "paper_name", "mean")
        if any(not row[k].strip() for k in required):
            raise AnalysisError(f"{where}: every one of {','.join(required)} needs a value")
        if row["kind"] not in PAPER_KINDS:
            raise AnalysisError(f"{where}: kind must be one of {', '.join(PAPER_KINDS)}, got {row['kind']!r}")
        table = _number(row["table"], "table", where, integer=True)
        cells.append(PaperCell(table, row["kind"], row["domain"], row["task"], row["paper_name"],
                               _number(row["mean"], "mean", where), _number(row["std"], "std", where),
                               _number(row["seeds"], "seeds", where, integer=True), row["note"]))
    return cells


def parse_methods(text: str, name: str = METHODS_FILE) -> list[PaperMethod]:
    """The rows of ``methods.csv``; a malformed row is an :class:`AnalysisError` naming the line."""
    methods = []
    for where, row in _rows(text, name, METHOD_FIELDS):
        flags = tuple(row["flags"].split())
        if len(flags) % 2 or any(not f.startswith("--") for f in flags[::2]):
            raise AnalysisError(f"{where}: flags must be pairs of --option value, got {row['flags']!r}")
        agent = row["agent"].strip()
        if agent and agent not in AGENTS:
            raise AnalysisError(f"{where}: unknown agent {agent!r}")
        if bool(agent) != bool(row["method"].strip()):
            raise AnalysisError(f"{where}: agent and method are given together or not at all")
        methods.append(PaperMethod(_number(row["table"], "table", where, integer=True), row["paper_name"], agent,
                                   flags, row["method"].strip(), tuple(row["sweep"].split()), row["note"]))
    return methods


def _read(file: str) -> str:
    try:
        return resources.files(DATA_PACKAGE).joinpath(*DATA_DIR, file).read_text(encoding="utf-8")
    except OSError as exc:
        raise AnalysisError(f"the paper's tables cannot be read from the dvfb package: {exc}") from exc


@dataclass(frozen=True)
class PaperTables:
    """The package data: every cell, and the mapping of each (table, paper_name) to dvfb."""

    cells: tuple[PaperCell, ...]
    methods: Mapping[tuple[int, str], PaperMethod]

    def method_of(self, cell: PaperCell) -> PaperMethod:
        return self.methods[(cell.table, cell.paper_name)]


def load_paper_tables() -> PaperTables:
    """``cells.csv`` and ``methods.csv`` of the package, checked: one cell per (table, domain, task,
    paper_name), one mapping per (table, paper_name), and every cell's column mapped."""
    cells = parse_cells(_read(CELLS_FILE))
    methods = parse_methods(_read(METHODS_FILE))
    if not cells:
        raise AnalysisError(f"the dvfb package holds no paper cells ({'/'.join(DATA_DIR)}/{CELLS_FILE}); "
                            "reinstall dvfb")
    seen: set[tuple] = set()
    for cell in cells:
        key = (cell.table, cell.domain, cell.task, cell.paper_name)
        if key in seen:
            raise AnalysisError(f"the paper tables list Table {cell.table}, {cell.domain} {cell.task}, "
                                f"{cell.paper_name} twice")
        seen.add(key)
    by_key: dict[tuple[int, str], PaperMethod] = {}
    for method in methods:
        if (method.table, method.paper_name) in by_key:
            raise AnalysisError(f"{METHODS_FILE} maps Table {method.table} {method.paper_name} twice")
        by_key[(method.table, method.paper_name)] = method
    columns = {(c.table, c.paper_name) for c in cells}
    unmapped = sorted(columns - set(by_key))
    if unmapped:
        raise AnalysisError(f"{METHODS_FILE} has no row for Table {unmapped[0][0]} {unmapped[0][1]}")
    extra = sorted(set(by_key) - columns)
    if extra:
        raise AnalysisError(f"{METHODS_FILE} maps Table {extra[0][0]} {extra[0][1]}, which has no cell")
    return PaperTables(tuple(cells), by_key)


# ---------------------------------------------------------------------------------------------
# the runs' budget


@dataclass(frozen=True)
class RunBudget:
    """What a report's numbers were trained with: presets, pre-training frames (offline: updates)
    behind the zero-shot and fine-tuning numbers, and fine-tuning frames at the last curve point."""

    presets: tuple[str, ...] = ()
    pretrain_frames: tuple[int, ...] = ()
    finetune_frames: tuple[int, ...] = ()
    offline: bool = False  # trained on a dataset: pretrain_frames count updates


def run_budget(runs: Runs, zeroshot: Iterable[Score], finetune: Iterable[Score]) -> RunBudget:
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
    return RunBudget(tuple(sorted(presets)), tuple(sorted(pretrain)), tuple(sorted(finetune_frames)))


def method_budgets(runs: Runs, zeroshot: Iterable[Score],
                   finetune: Iterable[Score]) -> dict[tuple[str, str], RunBudget]:
    """The budget behind each column of the report, keyed by (``zeroshot`` or ``finetune``, method)."""
    pretrain_runs = {str(r.path): r for r in runs.pretrain}
    finetune_runs = {str(r.path): r for r in runs.finetune}
    parts: dict[tuple[str, str], dict] = {}

    def add(key, config, pretrain_frames, finetune_frames=None):
        part = parts.setdefault(key, {"presets": set(), "pretrain": set(), "finetune": set(), "offline": False})
        part["presets"].add(str(getattr(config, "preset", "")))
        part["pretrain"].add(int(pretrain_frames))
        if finetune_frames is not None:
            part["finetune"].add(int(finetune_frames))
        part["offline"] |= bool(getattr(config, "dataset", ""))

    for score in zeroshot:
        run = pretrain_runs.get(str(score.source.parent.parent))  # RUN/zeroshot/<task>.json
        if run is not None:
            add(("zeroshot", score.method), run.config, score.pretrain_frames or run.config.frames)
    for score in finetune:
        run = finetune_runs.get(str(score.source.parent))  # RUN/finetune/<name>/curve.json
        if run is not None and run.parent is not None:
            add(("finetune", score.method), run.parent.config, score.pretrain_frames or run.parent.config.frames,
                score.frames)
    return {key: RunBudget(tuple(sorted(p for p in part["presets"] if p)), tuple(sorted(part["pretrain"])),
                        tuple(sorted(part["finetune"])), part["offline"]) for key, part in parts.items()}


def _frames(values: Sequence[int]) -> str:
    return ", ".join(f"{v:,}" for v in values)


def _short(value: int) -> str:
    """100000 -> 100k, 2000000 -> 2M, 1500 -> 1.5k."""
    for size, unit in ((1_000_000, "M"), (1_000, "k")):
        if value >= size:
            return f"{value / size:g}{unit}"
    return str(value)


def scale_marker(budget: RunBudget | None, kind: str) -> str:
    """How the runs behind one column compare with the paper's budget, for the comparison's
    ``runs vs paper`` cell: ``paper scale``, or what is below it."""
    if budget is None:
        return "–"
    parts = []
    if budget.offline:
        parts.append(f"offline, {'/'.join(_short(f) for f in budget.pretrain_frames)} updates")
    else:
        small = [f for f in budget.pretrain_frames if f < PAPER_PRETRAIN_FRAMES]
        if small:
            parts.append(f"{'/'.join(_short(f) for f in small)} of {_short(PAPER_PRETRAIN_FRAMES)} frames")
    reduced = [p for p in budget.presets if p not in FULL_SIZE_PRESETS]
    if reduced:
        parts.append(f"preset {', '.join(reduced)}")
    short = [f for f in budget.finetune_frames if f < PAPER_FINETUNE_FRAMES]
    if kind == "finetune" and short:
        parts.append(f"fine-tuned {'/'.join(_short(f) for f in short)} of {_short(PAPER_FINETUNE_FRAMES)} frames")
    return "; ".join(parts) if parts else PAPER_SCALE


def scale_notes(budget: RunBudget, has_finetune: bool) -> list[str]:
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
class CellComparison:
    """One of the paper's cells beside one column of the report (or none: ``not run``, ``paper only``)."""

    cell: PaperCell
    status: str  # compared, incomplete, not run or paper only
    method: str = ""  # the report's column
    report: Summary | None = None
    scale: str = ""  # the runs behind the column against the paper's budget (scale_marker)
    detail: str = ""  # for incomplete: what the report has

    @property
    def difference(self) -> float | None:
        return None if self.report is None else self.report.mean - self.cell.mean


def _all_domains(cell: PaperCell, cells: Sequence[PaperCell]) -> list[str]:
    """The domains an ``all`` row of a table averages over: those of the table's other cells of the column."""
    return list(dict.fromkeys(c.domain for c in cells if c.table == cell.table and c.paper_name == cell.paper_name
                              and c.domain != ALL_DOMAINS))


def _columns(method: PaperMethod, presets: Sequence[str], domain: str, kind: str, table: Table) -> list[str]:
    """The columns of ``table`` that a run of the method's flags makes under one of ``presets`` and
    that have a value on ``domain``: the method's column, or each of its pre-training budgets' columns
    where the report keeps them apart (``fb (1,200 frames)``, docs/reports.md)."""
    labels = dict.fromkeys(label for preset in presets if (label := method.label(preset, domain, kind)) is not None)
    tasks = [task for d, task in table.rows if d == domain]
    return [column for column in table.columns if split_budget_label(column)[0] in labels
            and any(table.cell(domain, task, column) is not None for task in tasks)]


def _domain_average(table: Table, domain: str, label: str) -> tuple[Summary | None, str]:
    """The column's average on the domain, or None and what it lacks."""
    cell = table.cell(domain, AVERAGE, label)
    if cell is not None:
        return cell, ""
    tasks = [task for d, task in table.rows if d == domain and task != AVERAGE]
    have = [task for task in tasks if table.cell(domain, task, label) is not None]
    return None, f"{len(have)} of {len(tasks)} tasks" if have else ""


def compare_table(table: Table | None, kind: str, *, metric: str = RETURN,
                  budgets: Mapping[str, RunBudget] | None = None, presets: Sequence[str] = ("paper",),
                  tables: PaperTables | None = None) -> list[CellComparison]:
    """Every paper cell of ``kind`` (``zeroshot`` or ``finetune``) and ``metric`` beside the column of
    ``table`` that its method and flags make under ``presets`` (the presets of the table's runs):
    one row per cell and matching column, or one ``not run`` row.

    ``budgets`` maps the table's columns to the budget of their runs (:func:`method_budgets`, or one
    snapshot's), which gives each row's ``scale``. Per task the report's value is the column's cell;
    per average its ``average`` row; Table 5's averages over all domains are the mean of the domain
    averages (each domain has four tasks, so this is the mean of the twelve task means the paper takes).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}")
    tables = load_paper_tables() if tables is None else tables
    budgets = budgets or {}
    rows: list[CellComparison] = []
    for cell in tables.cells:
        if cell.report_kind != kind or cell.metric != metric:
            continue
        method = tables.method_of(cell)
        if not method.agent:
            rows.append(CellComparison(cell, PAPER_ONLY))
            continue
        if table is None:
            rows.append(CellComparison(cell, NOT_RUN))
            continue
        if cell.domain == ALL_DOMAINS:
            rows.append(_all_domains_row(cell, method, table, kind, presets, budgets, tables.cells))
            continue
        matched = _columns(method, presets, cell.domain, kind, table)
        if not matched:
            rows.append(CellComparison(cell, NOT_RUN))
        for label in matched:
            scale = scale_marker(budgets.get(label), kind)
            if cell.is_average:
                value, lacking = _domain_average(table, cell.domain, label)
                status = COMPARED if value is not None else (INCOMPLETE if lacking else NOT_RUN)
                rows.append(CellComparison(cell, status, label, value, scale, lacking))
            else:
                value = table.cell(cell.domain, cell.report_task, label)
                rows.append(CellComparison(cell, COMPARED if value is not None else NOT_RUN, label, value, scale))
    return rows


def _all_domains_row(cell, method, table, kind, presets, budgets, cells) -> CellComparison:
    domains = _all_domains(cell, cells)
    labels, averages = [], []
    for domain in domains:
        matched = _columns(method, presets, domain, kind, table)
        if matched:
            labels.append(matched[0])
            value, _ = _domain_average(table, domain, matched[0])
            if value is not None:
                averages.append(value)
    if not labels:
        return CellComparison(cell, NOT_RUN)
    merged = [budgets[label] for label in labels if label in budgets]
    budget = RunBudget(tuple(sorted({p for b in merged for p in b.presets})),
                    tuple(sorted({f for b in merged for f in b.pretrain_frames})),
                    tuple(sorted({f for b in merged for f in b.finetune_frames})),
                    any(b.offline for b in merged)) if merged else None
    name = ", ".join(dict.fromkeys(labels))
    if len(averages) < len(domains):
        return CellComparison(cell, INCOMPLETE, name, None, scale_marker(budget, kind),
                              f"{len(averages)} of {len(domains)} domain averages")
    value = Summary(float(sum(a.mean for a in averages) / len(averages)), float("nan"), min(a.n for a in averages))
    return CellComparison(cell, COMPARED, name, value, scale_marker(budget, kind))


@dataclass
class PaperComparison:
    rows: list[CellComparison]
    budget: RunBudget
    notes: list[str] = field(default_factory=list)
    tables: PaperTables | None = None

    @property
    def compared(self) -> list[CellComparison]:
        return [r for r in self.rows if r.status == COMPARED]

    @property
    def matched(self) -> list[CellComparison]:
        """The rows of the paper's columns that this report has (compared or incomplete)."""
        return [r for r in self.rows if r.method]


def compare(zeroshot: Table | None, finetune: Table | None, budget: RunBudget, *,
            success_zeroshot: Table | None = None, success_finetune: Table | None = None,
            budgets: Mapping[tuple[str, str], RunBudget] | None = None,
            tables: PaperTables | None = None) -> PaperComparison:
    """Every paper cell beside the report's tables: returns against Tables 1 and 2 of the report,
    Meta-World's success rates against its Table 6 (:func:`compare_table` for each), with the
    notes: the budget first, then what the paper has that the report does not, and the sweeps that
    make it."""
    tables = load_paper_tables() if tables is None else tables
    budgets = budgets or {}
    presets = budget.presets or ("paper",)
    rows: list[CellComparison] = []
    for kind, metric, table in (("zeroshot", RETURN, zeroshot), ("finetune", RETURN, finetune),
                                ("zeroshot", SUCCESS, success_zeroshot), ("finetune", SUCCESS, success_finetune)):
        own = {method: b for (k, method), b in budgets.items() if k == kind}
        rows += compare_table(table, kind, metric=metric, budgets=own, presets=presets, tables=tables)
    comparison = PaperComparison(rows, budget, scale_notes(budget, finetune is not None), tables)
    matched = {(r.cell.report_kind, r.method) for r in rows if r.method}
    for kind, table in (("zeroshot", zeroshot), ("finetune", finetune)):
        extra = [m for m in (table.columns if table is not None else ()) if m != "random" and (kind, m) not in matched]
        if extra:
            comparison.notes.append(f"no cell of the paper for the {kind} column(s) {', '.join(extra)} "
                                    "(docs/reproduce.md lists the paper's columns and their flags)")
    absent: dict[int, dict[str, None]] = {}
    for row in rows:
        if row.status == NOT_RUN and not any(r.method for r in rows if r.cell.table == row.cell.table
                                             and r.cell.paper_name == row.cell.paper_name):
            absent.setdefault(row.cell.table, {})[row.cell.paper_name] = None
    if absent:
        parts = []
        for number, names in sorted(absent.items()):
            sweeps = dict.fromkeys(s for name in names for s in tables.methods[(number, name)].sweeps)
            parts.append(f"Table {number} ({', '.join(names)}: {', '.join(f'sweeps/paper/{s}' for s in sweeps)})")
        comparison.notes.append("not run here, with the sweep files that run them: " + "; ".join(parts))
    if any(r.status == INCOMPLETE for r in rows):
        comparison.notes.append("'incomplete': the report lacks some of the domain's tasks for that column, so it "
                                "has no average (docs/tasks.md lists the tasks)")
    if any(r.status == PAPER_ONLY for r in rows):
        comparison.notes.append("Table 5's 'Average of best' of LAP, LRA-P, LRA-SR and Offline FB takes, per domain, "
                                "the best of three dataset columns; compare those columns ('paper only')")
    return comparison


# ---------------------------------------------------------------------------------------------
# output


def _value(mean: float | None, std: float | None, seeds: int | None, digits: int) -> str:
    if mean is None:
        return "–"
    text = f"{mean:.{digits}f}"
    if std is not None and not math.isnan(std):
        text += f" ± {std:.{digits}f}"
    return text + (f" ({seeds})" if seeds is not None else "")


def _paper_value(cell: PaperCell) -> str:
    text = f"{cell.mean:g}" + (f" ± {cell.std:g}" if cell.std is not None else "")
    return text + (f" ({cell.seeds})" if cell.seeds is not None else "")


def _digits(cell: PaperCell) -> int:
    return 2 if cell.metric == SUCCESS else 1


def _report_value(row: CellComparison) -> str:
    if row.report is None:
        return f"– ({row.detail})" if row.detail else "–"
    return _value(row.report.mean, row.report.std, row.report.n, _digits(row.cell))


def _difference(row: CellComparison) -> str:
    return "–" if row.difference is None else f"{row.difference:+.{_digits(row.cell)}f}"


class _Footnotes:
    """The paper's notes as numbered marks ``[n]`` after the paper's value, listed once below."""

    def __init__(self):
        self.numbers: dict[str, int] = {}

    def mark(self, note: str) -> str:
        if not note:
            return ""
        return f" [{self.numbers.setdefault(note, len(self.numbers) + 1)}]"

    def lines(self) -> list[str]:
        return [f"[{n}] {note}" for note, n in self.numbers.items()]


def _heading(table: int, domain: str) -> str:
    where = "all domains" if domain == ALL_DOMAINS else domain
    return f"Table {table} ({TABLE_TITLES.get(table, 'paper')}), {where}"


def cells_markdown(rows: Sequence[CellComparison], heading_level: int = 3, notes: _Footnotes | None = None) -> str:
    """Per-task markdown tables of comparison rows, one per (paper table, domain), each under its
    heading with the paper's budget for it; each row is a task (or the average) of one column:
    this report's mean ± std (seeds), the paper's, the difference and ``runs vs paper``. Rows of
    columns the report lacks (``not run``, ``paper only``) are left out."""
    own = notes is None
    notes = _Footnotes() if notes is None else notes
    groups: dict[tuple[int, str], list[CellComparison]] = {}
    for row in rows:
        if row.method:
            groups.setdefault((row.cell.table, row.cell.domain), []).append(row)
    hashes = "#" * heading_level
    lines: list[str] = []
    for (table, domain), group in groups.items():
        lines += [f"{hashes} {_heading(table, domain)}", "", f"The paper: {PAPER_BUDGETS.get(table, 'not stated')}.",
                  "", "| task | method | paper's name | this report | paper | difference | runs vs paper |",
                  "|---|---|---|---:|---:|---:|---|"]
        for row in group:
            task = f"**{row.cell.task.replace('_', ' ')}**" if row.cell.is_average else row.cell.report_task
            lines.append(f"| {task} | {row.method} | {row.cell.paper_name} | {_report_value(row)} | "
                         f"{_paper_value(row.cell)}{notes.mark(row.cell.note)} | {_difference(row)} | {row.scale} |")
        lines.append("")
    if own and notes.numbers:
        lines += ["The paper's notes:", ""] + [f"- {line}" for line in notes.lines()]
    return "\n".join(lines).rstrip()


def to_markdown(comparison: PaperComparison, heading_level: int = 2) -> str:
    """The comparison as a markdown section: the scale note, the per-task tables of the paper's
    columns this report has, the domain averages in one table, then the notes."""
    hashes = "#" * heading_level
    notes = _Footnotes()
    lines = [f"{hashes} Comparison with the paper's numbers", "", comparison.notes[0], "",
             "Every cell of the paper's results tables (Tables 1, 2 and 5-12) whose method and flags this report "
             "has, beside the report's column of that method (docs/reproduce.md): this report's mean ± std over "
             "seeds (ddof 1; seeds in brackets), the paper's mean ± std (its seeds), the difference (this report "
             "minus the paper), and how the runs behind the column compare with the paper's budget (`runs vs "
             "paper`: pre-training frames of its 2M, the preset, fine-tuning frames of its 100k; `paper scale` "
             "where they match). Episode returns; Meta-World cells are success rates (0 to 1). "
             "paper_comparison.csv has every cell of the paper, run here or not.", ""]
    per_task = cells_markdown(comparison.rows, heading_level + 1, notes)
    lines += [per_task, ""] if per_task else ["No column of this report is one of the paper's.", ""]
    averages = [r for r in comparison.rows if r.cell.is_average and r.method]
    if averages:
        lines += [f"{hashes}# Averages", "",
                  "| table | domain | method | paper's name | this report | seeds | paper | difference | status | "
                  "runs vs paper |", "|---:|---|---|---|---:|---:|---:|---:|---|---|"]
        for row in averages:
            value = "–" if row.report is None else f"{row.report.mean:.{_digits(row.cell)}f}"
            status = row.status + (f" ({row.detail})" if row.detail else "")
            seeds = "–" if row.report is None else row.report.n
            lines.append(f"| {row.cell.table} | {row.cell.domain} | {row.method} | {row.cell.paper_name} | {value} | "
                         f"{seeds} | {row.cell.mean:g}{notes.mark(row.cell.note)} | {_difference(row)} | {status} | "
                         f"{row.scale} |")
        lines.append("")
    if notes.numbers:
        lines += ["The paper's notes:", ""] + [f"- {line}" for line in notes.lines()] + [""]
    if len(comparison.notes) > 1:
        lines += [f"- {note}" for note in comparison.notes[1:]]
    return "\n".join(lines).rstrip()


def to_csv(comparison: PaperComparison) -> str:
    """One line per comparison row (:data:`CSV_FIELDS`): every cell of the paper, once per report
    column it is compared with, or once with an empty method; numbers in full precision, empty
    where there is none."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_FIELDS)

    def number(value: float | int | None) -> str:
        return "" if value is None or (isinstance(value, float) and math.isnan(value)) else repr(value)

    for row in comparison.rows:
        c, r = row.cell, row.report
        status = row.status + (f" ({row.detail})" if row.detail else "")
        writer.writerow([c.table, c.kind, c.domain, c.task, c.paper_name, row.method,
                         number(None if r is None else r.mean), number(None if r is None else r.std),
                         "" if r is None else r.n, number(c.mean), number(c.std), "" if c.seeds is None else c.seeds,
                         number(row.difference), status, row.scale, c.note])
    return out.getvalue()
