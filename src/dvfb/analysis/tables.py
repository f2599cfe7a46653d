"""Result tables shaped like the paper's Table 1 (zero-shot), Table 2 (fine-tuning) and Table 6
(success rates on the Meta-World tasks, docs/tasks.md §4.6).

Rows are the tasks of every domain that appears in the inputs (registry order, docs/tasks.md §0), each
domain followed by an ``average`` row; columns are methods (named by
:func:`dvfb.analysis.common.method_name`), plus ``random`` when random-policy files are given.

Statistics (docs/methods.md §8.3: "mean ± std over seeds"):

* a cell is the mean over seeds of the per-seed score, ± the **sample standard deviation over
  seeds (ddof = 1)**, or ± the standard error ``std(ddof=1) / sqrt(n)`` with ``spread="se"``.
  With one seed the spread is undefined and the cell shows the mean alone;
* a domain's ``average`` is the mean of its task means; it needs a value on every task of the
  domain's rows (otherwise it is a gap). Its spread is taken over the per-seed task averages of the
  seeds that have every task;
* expert-normalised scores divide every per-seed return by the URLB expert return of the task
  (:data:`EXPERT_RETURNS`) and are shown in percent; tasks without an expert return are gaps.

Missing results are gaps (``–`` in markdown, an empty cell in CSV), never zeros.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from dvfb.analysis.common import Score, method_sort_key
from dvfb.analysis.normalise import NORMALISERS, Normaliser
from dvfb.analysis.normalise import normalisers as available_normalisers
from dvfb.envs.registry import DOMAINS, tasks_of_domain

GAP = "–"
SPREADS = ("std", "se")
STD_DDOF = 1

AVERAGE = "average"


@dataclass(frozen=True)
class Summary:
    """The seeds' mean and spread of one entry of a table (a task or an average, a method); ``n`` is
    the number of seeds. (A sweep's grid cell is :class:`dvfb.sweep.spec.Cell`.)"""

    mean: float
    std: float  # ddof = 1; NaN when n == 1
    n: int

    @property
    def se(self) -> float:
        return self.std / math.sqrt(self.n) if self.n > 1 else float("nan")

    def spread(self, kind: str) -> float:
        return self.se if kind == "se" else self.std


def summarise(values: Sequence[float]) -> Summary:
    """Mean and sample std (ddof=1) of per-seed values."""
    array = np.asarray(values, dtype=float)
    if array.size == 0:
        raise ValueError("no values to summarise")
    std = float(np.std(array, ddof=STD_DDOF)) if array.size > 1 else float("nan")
    return Summary(float(array.mean()), std, int(array.size))


@dataclass
class Table:
    """A table: ``rows`` of (domain, task) including average rows, ``columns`` of methods, cells."""

    title: str
    rows: list[tuple[str, str]]
    columns: list[str]
    cells: dict[tuple[str, str], Summary]  # (task or f"{domain}/average", method) -> Summary
    normalised_by: dict[str, dict[tuple[str, str], Summary]]  # normaliser name -> cells (docs/reports.md)
    spread: str = "std"
    digits: int = 1  # decimals shown in markdown (success rates: 2)
    normalisers: dict[str, Normaliser] = dataclasses.field(default_factory=dict)
    episodes: dict[str, list[int]] = dataclasses.field(default_factory=dict)  # method -> episodes per result

    @property
    def normalised(self) -> dict[tuple[str, str], Summary]:
        """The expert-normalised cells (the paper's normalised scores)."""
        return self.normalised_by.get("expert", {})

    @staticmethod
    def row_key(domain: str, task: str) -> str:
        return f"{domain}/{AVERAGE}" if task == AVERAGE else task

    def cell(self, domain: str, task: str, method: str, normalised: bool | str = False) -> Summary | None:
        return self.cells_of(normalised).get((self.row_key(domain, task), method))

    def cells_of(self, normalised: bool | str = False) -> dict[tuple[str, str], Summary]:
        """Raw cells (False), expert-normalised ones (True) or those of a named normaliser."""
        if normalised is False:
            return self.cells
        return self.normalised_by.get("expert" if normalised is True else normalised, {})


def _domains_and_tasks(scores: Iterable[Score]) -> list[tuple[str, list[str]]]:
    """Domains in registry order with all their tasks; unknown domains keep the tasks seen."""

    seen: dict[str, set[str]] = defaultdict(set)
    for score in scores:
        seen[score.domain].add(score.task)
    ordered = [d for d in DOMAINS if d in seen] + sorted(d for d in seen if d not in DOMAINS)
    result = []
    for domain in ordered:
        tasks = tasks_of_domain(domain) if domain in DOMAINS else []
        tasks = tasks + sorted(t for t in seen[domain] if t not in tasks)
        result.append((domain, tasks))
    return result


def build_table(scores: Sequence[Score], title: str, spread: str = "std", digits: int = 1,
                normalisers: dict[str, Normaliser] | None = None) -> Table:
    """Aggregate scores (already checked for duplicates) into a :class:`Table`, with a normalised
    variant per normaliser (default: those the scores allow, :func:`dvfb.analysis.normalise.normalisers`)."""
    if spread not in SPREADS:
        raise ValueError(f"spread must be one of {SPREADS}")
    normalisers = available_normalisers(scores) if normalisers is None else normalisers
    per_cell: dict[tuple[str, str], dict] = defaultdict(dict)  # (task, method) -> {seed: value}
    episodes: dict[str, set[int]] = defaultdict(set)
    for score in scores:
        per_cell[(score.task, score.method)][score.seed] = score.value
        if score.episodes is not None:
            episodes[score.method].add(score.episodes)
    columns = sorted({s.method for s in scores}, key=method_sort_key)
    rows: list[tuple[str, str]] = []
    cells: dict[tuple[str, str], Summary] = {}
    normalised: dict[str, dict[tuple[str, str], Summary]] = {name: {} for name in normalisers}
    for domain, tasks in _domains_and_tasks(scores):
        rows.extend((domain, task) for task in tasks)
        rows.append((domain, AVERAGE))
        for method in columns:
            by_seed = {task: per_cell.get((task, method), {}) for task in tasks}
            for task in tasks:
                if by_seed[task]:
                    values = list(by_seed[task].values())
                    cells[(task, method)] = summarise(values)
                    for name, norm in normalisers.items():
                        if norm.covers(task):
                            normalised[name][(task, method)] = summarise([norm(task, v) for v in values])
            if all(by_seed[task] for task in tasks):
                key = (f"{domain}/{AVERAGE}", method)
                cells[key] = _average(tasks, by_seed, lambda task, v: v)
                for name, norm in normalisers.items():
                    if all(norm.covers(task) for task in tasks):
                        normalised[name][key] = _average(tasks, by_seed, norm)
    return Table(title, rows, columns, cells, normalised, spread, digits, dict(normalisers),
                 {m: sorted(e) for m, e in episodes.items()})


def _average(tasks: list[str], by_seed: dict[str, dict], transform) -> Summary:
    """Mean of the task means; spread over the per-seed averages of seeds present on every task."""
    task_means = [float(np.mean([transform(task, v) for v in by_seed[task].values()])) for task in tasks]
    complete = set.intersection(*(set(by_seed[task]) for task in tasks))
    per_seed = [float(np.mean([transform(task, by_seed[task][seed]) for task in tasks]))
                for seed in sorted(complete, key=repr)]
    std = float(np.std(per_seed, ddof=STD_DDOF)) if len(per_seed) > 1 else float("nan")
    return Summary(float(np.mean(task_means)), std, len(per_seed))


# ---------------------------------------------------------------------------------------------
# formatting


def format_cell(cell: Summary | None, spread: str, digits: int = 1) -> str:
    if cell is None:
        return GAP
    value = cell.spread(spread)
    if math.isnan(value):
        return f"{cell.mean:.{digits}f}"
    return f"{cell.mean:.{digits}f} ± {value:.{digits}f}"


def _spread_words(spread: str) -> str:
    return ("standard error over seeds (std with ddof=1 divided by sqrt(n))" if spread == "se"
            else "standard deviation over seeds (ddof=1)")


def to_markdown(table: Table, normalised: bool | str = False) -> str:
    """One markdown table: domain | task | method columns; gaps as ``–``."""
    cells = table.cells_of(normalised)
    header = ["domain", "task", *table.columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---", "---"] + ["---:"] * len(table.columns)) + "|"]
    for domain, task in table.rows:
        label = f"**{AVERAGE}**" if task == AVERAGE else task
        values = [format_cell(cells.get((table.row_key(domain, task), m)), table.spread, table.digits)
                  for m in table.columns]
        lines.append("| " + " | ".join([domain, label, *values]) + " |")
    return "\n".join(lines)


def table_markdown_section(table: Table, heading_level: int = 2) -> str:
    """The raw-return table and the expert-normalised table with their captions."""
    hashes = "#" * heading_level
    spread = _spread_words(table.spread)
    parts = [
        f"{hashes} {table.title}",
        "",
        f"Episode return: mean ± {spread}. `–`: no result. {sample_sizes(table)}",
        "",
        to_markdown(table),
        "",
        f"{hashes}# {table.title}: expert-normalised score",
        "",
        "Percent of the URLB expert return (walker stand/walk/run/flip 984/971/796/799, quadruped "
        "stand/walk/jump/run 920/866/888/888); other domains have no expert return (`–`). "
        f"Mean ± {spread}.",
        "",
        to_markdown(table, normalised=True),
    ]
    for name in NORMALISERS[1:]:
        if table.normalised_by.get(name):
            parts += ["", f"{hashes}# {table.title}: {NORMALISED_TITLES[name]}", "",
                      f"Normaliser: {table.normalisers[name].description}; tasks without it are gaps (`–`). "
                      f"Mean ± {spread}.", "", to_markdown(table, normalised=name)]
    return "\n".join(parts)


NORMALISED_TITLES = {"supervised": "percent of the supervised reference", "minmax": "min-max score (random 0, supervised 100)"}


def sample_sizes(table: Table) -> str:
    """What stands behind the cells: seeds per cell and evaluation episodes per result, per column."""
    def counts(values: set[int]) -> str:
        return "/".join(str(v) for v in sorted(values))

    seeds: dict[str, set[int]] = defaultdict(set)
    for (row, method), cell in table.cells.items():
        if not row.endswith(f"/{AVERAGE}"):
            seeds[method].add(cell.n)
    parts = []
    for method in table.columns:
        episodes = table.episodes.get(method)
        parts.append(f"{method} {counts(seeds[method])} seed{'s' if seeds[method] != {1} else ''}"
                     + (f" × {counts(set(episodes))} episodes" if episodes else ""))
    return "Behind each cell: " + "; ".join(parts) + "."


def success_markdown_section(table: Table, heading_level: int = 2) -> str:
    """A success-rate table (paper Table 6 shape) with its caption; no normalised variant."""
    hashes = "#" * heading_level
    return "\n".join([
        f"{hashes} {table.title}",
        "",
        "Success rate: the fraction of evaluation episodes that end in success, read at the final "
        f"(250th) step (docs/tasks.md §4.6); mean ± {_spread_words(table.spread)}. `–`: no result.",
        "",
        to_markdown(table),
    ])


def to_csv(table: Table, normalised: bool | str = False) -> str:
    """A wide CSV: domain, task, then ``<method>_mean``, ``_std`` or ``_se``, ``_n`` per method.

    Numbers are written in full precision; gaps are empty cells.
    """
    cells = table.cells_of(normalised)
    spread = table.spread
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    header = ["domain", "task"]
    for method in table.columns:
        header += [f"{method}_mean", f"{method}_{spread}", f"{method}_n"]
    writer.writerow(header)
    for domain, task in table.rows:
        row = [domain, task]
        for method in table.columns:
            cell = cells.get((table.row_key(domain, task), method))
            if cell is None:
                row += ["", "", ""]
            else:
                value = cell.spread(spread)
                row += [repr(cell.mean), "" if math.isnan(value) else repr(value), str(cell.n)]
        writer.writerow(row)
    return out.getvalue()
