"""Run discovery, method names and result records shared by the reports and analyses.

* :func:`method_name` -- the one place that turns run configs into a method label, by asking the
  agent registry (``dvfb``, ``dvfb_wo_ce``, ``fb``, ``rnd``, ..., with ``_wo_svf`` / ``_wo_map``
  for the FB family's fine-tuning ablations).
* :func:`discover_runs` -- the pre-training and fine-tuning runs under any mix of run directories
  and parent directories, found and read by the runs layer (:mod:`dvfb.runs.layout`).
* :func:`collect_scores` -- one :class:`Score` per (method, seed, task) from the zero-shot result
  files, the last point of each fine-tuning curve, and random-policy files; two files claiming the
  same (method, seed, task) are an error that names both.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from dvfb.agents import AGENTS, get_spec
from dvfb.core.config import to_dict
from dvfb.core.errors import DvfbError
from dvfb.core.files import read_json
from dvfb.protocols import finetuner_class
from dvfb.runs.layout import discover
from dvfb.runs.presets import preset_config

log = logging.getLogger(__name__)

class AnalysisError(DvfbError):
    """Bad input to a report or an analysis (no runs found, duplicate results, unreadable files)."""


# ---------------------------------------------------------------------------------------------
# method names


def method_name(run_config: Any, finetune: Any | None = None) -> str:
    """The method label of a run, from its configs (dataclasses or their dicts).

    The registry decides: each method's :class:`~dvfb.agents.registry.AgentSpec` names its variants
    (DVFB: ``dvfb_wo_ce`` for ``use_ce = false``, ``dvfb_<reward>`` for the Table 8 rewards; the FB
    family's fine-tuning ablations append ``_wo_svf`` and ``_wo_map``). A run trained offline on a
    dataset appends ``@`` and the dataset directory's name (``vcfb@rnd_walker``). ``run_config`` is the
    pre-training run's config; ``finetune`` a fine-tuning run's ``finetune`` section. A coefficient
    the registry lists (``AgentSpec.coefficients``) whose value differs from the run's preset adds
    its own suffix (:func:`coefficient_suffix`), so that the paper's ablations are columns of their own.
    """

    agent = _field(run_config, "agent", None)
    try:
        spec = get_spec(agent)
    except DvfbError:
        return str(agent)
    label = spec.method_label(run_config, finetune) + coefficient_suffix(spec, run_config, finetune)
    dataset = _field(run_config, "dataset", None)
    if dataset:  # offline: the method on a dataset is its own row (docs/methods.md, "Offline training")
        label += "@" + Path(dataset).name
    return label


def _field(config: Any, name: str, default: Any) -> Any:
    if isinstance(config, dict):
        return config.get(name, default)
    return getattr(config, name, default)


def coefficient_suffix(spec: Any, run_config: Any, finetune: Any | None = None) -> str:
    """``_alpha3``, ``_beta0.7``, ``_eta0.02``, ``_eta_adaptive``, ...: one part per coefficient of
    ``spec.coefficients`` whose value differs from the run's preset (fine-tuning coefficients only
    for a fine-tuning run, from its ``finetune`` section), in the registry's order. A value the
    registry's own label already names (eta 0: ``_wo_svf``) adds nothing; a run without a known
    preset adds nothing."""
    reference = _preset_reference(spec.name, _field(run_config, "preset", None)) if spec.coefficients else None
    if reference is None:
        return ""
    parts = []
    for dotted, short in spec.coefficients:
        section, _, name = dotted.partition(".")
        source = finetune if section == "finetune" else _field(run_config, section, None)
        value = None if source is None else _field(source, name, None)
        base = reference.get(section, {}).get(name)
        if value is None or base is None or value == base:
            continue
        if _labelled_by_registry(spec, run_config, finetune, section, name, base):
            continue
        parts.append(f"_{short}{value:g}" if isinstance(value, (int, float)) else f"_{short}_{value}")
    return "".join(parts)


@functools.lru_cache(maxsize=None)
def _preset_dict(agent: str, preset: str) -> dict | None:
    try:
        return to_dict(preset_config(preset, agent))
    except DvfbError:
        return None


def _preset_reference(agent: str, preset: Any) -> dict | None:
    """The run config of ``preset`` for ``agent`` as a dict (None: not a preset of the method)."""
    return _preset_dict(agent, preset) if isinstance(preset, str) and preset else None


def _labelled_by_registry(spec: Any, run_config: Any, finetune: Any, section: str, name: str, base: Any) -> bool:
    """Whether the registry's label changes when the field goes back to its preset value."""
    def with_base(config: Any) -> dict:
        data = dict(config) if isinstance(config, dict) else to_dict(config)
        return {**data, name: base}

    if section == "finetune":
        return spec.method_label(run_config, with_base(finetune)) != spec.method_label(run_config, finetune)
    data = dict(run_config) if isinstance(run_config, dict) else to_dict(run_config)
    changed = {**data, section: with_base(data.get(section) or {})}
    return spec.method_label(changed, finetune) != spec.method_label(run_config, finetune)


def method_sort_key(name: str) -> tuple:
    """Column order of the tables: registered methods by their ``column`` (then registry order),
    each followed by its variants, then unknown names, random last; the budgets of one method
    (:func:`budget_label`) side by side, the smaller first."""

    if name == "random":
        return (3, 0, 0, 0, name, 0)
    base, frames = split_budget_label(name)
    names = list(AGENTS)
    # The longest registered name the label starts with: "dvfb_wo_ce" belongs to "dvfb", the
    # paper's "SF-Lap" to "sf"; an offline run's "@dataset" does not count.
    key = base.split("@", 1)[0].lower().replace("-", "_")
    owners = [n for n in names if key == n or key.startswith(n + "_") or key.replace("_", "") == n]
    if owners:
        owner = max(owners, key=len)
        return (0, AGENTS[owner].column, names.index(owner), len(base), base, frames or 0)
    return (2, 0, 0, 0, base, frames or 0)


_BUDGET = re.compile(r"^(?P<method>.+) \((?P<frames>[0-9,]+) frames\)$")


def budget_label(method: str, frames: int) -> str:
    """The column of ``method``'s numbers from the pre-training snapshot at ``frames`` frames, where a
    table has the method at several budgets (:func:`split_budgets`): ``fb (100,000 frames)``."""
    return f"{method} ({frames:,} frames)"


def split_budget_label(label: str) -> tuple[str, int | None]:
    """The method and the budget of a :func:`budget_label` (the label itself and None otherwise)."""
    match = _BUDGET.match(label)
    if match is None:
        return label, None
    return match["method"], int(match["frames"].replace(",", ""))


# ---------------------------------------------------------------------------------------------
# discovery


@dataclass
class PretrainEntry:
    """A pre-training run of a report: its run directory (:class:`dvfb.runs.layout.PretrainRun`)."""

    run: Any

    @property
    def path(self) -> Path:
        return self.run.path

    @property
    def config(self) -> Any:
        return self.run.config

    @property
    def method(self) -> str:
        return method_name(self.config)


@dataclass
class FinetuneEntry:
    """A fine-tuning run of a report (:class:`dvfb.runs.layout.FinetuneRun`) and its pre-training run
    where it was found."""

    run: Any
    parent: PretrainEntry | None = None

    @property
    def path(self) -> Path:
        return self.run.path

    @property
    def config(self) -> Any:
        return self.run.config

    @property
    def method(self) -> str:
        # The pre-training run's config names the variant (e.g. w/o CE); without it, the agent.
        pretrain = self.parent.config if self.parent is not None else {"agent": self.config.agent}
        name = method_name(pretrain, self.config.finetune)
        if not self.config.own_protocol:  # a fine-tuner chosen instead of the method's own: its own row (dvfb+lola)
            name += "+" + finetuner_class(self.config.protocol).label(self.config.finetune)
        return name

    @property
    def pretrain_seed(self) -> int | None:
        return self.parent.config.seed if self.parent is not None else None


@dataclass
class Runs:
    pretrain: list[PretrainEntry] = field(default_factory=list)
    finetune: list[FinetuneEntry] = field(default_factory=list)


def discover_runs(paths: Sequence[str | os.PathLike]) -> Runs:
    """Every pre-training and fine-tuning run in or under ``paths`` (:func:`dvfb.runs.layout.discover`).
    Raises :class:`AnalysisError` if a path does not exist or is not a directory."""
    pretrain, finetune = discover(paths, AnalysisError)
    wrapped = {id(run): PretrainEntry(run) for run in pretrain}
    return Runs([wrapped[id(run)] for run in pretrain],
                [FinetuneEntry(run, None if parent is None else wrapped.get(id(parent), PretrainEntry(parent)))
                 for run, parent in finetune])


# ---------------------------------------------------------------------------------------------
# scores


@dataclass(frozen=True)
class Score:
    """One number of a table: the return (or success rate) of one method, seed and task, and the
    file it came from."""

    kind: str  # "zeroshot", "finetune" or "random"
    method: str
    domain: str
    task: str
    seed: Any  # int, or (pretrain seed, fine-tuning seed) for fine-tuning runs
    value: float
    source: Path
    frames: int | None = None  # fine-tuning frames of the point (Table 2)
    pretrain_frames: int | None = None  # the pre-training snapshot the number comes from
    episodes: int | None = None  # evaluation episodes behind the value


def _episodes(returns: Any) -> int | None:
    return len(returns) if isinstance(returns, list) else None


def read_json_object(path: Path) -> dict:
    data = read_json(path, AnalysisError)
    if not isinstance(data, dict):
        raise AnalysisError(f"{path} does not hold a JSON object")
    return data


def _number(path: Path, data: dict, key: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise AnalysisError(f"{path}: {key!r} is missing or not a number")
    return float(value)


RETURN = "mean_return"
SUCCESS = "success_rate"
METRICS = (RETURN, SUCCESS)


def _has(data: dict, metric: str) -> bool:
    """Every result has a return; only tasks with a success criterion (Meta-World) a success rate."""
    return metric == RETURN or metric in data


def zeroshot_scores(runs: Iterable[PretrainEntry], metric: str = RETURN, every_snapshot: bool = False) -> list[Score]:
    """The final-snapshot zero-shot results ``RUN/zeroshot/<task>.json`` (paper Table 1; with
    ``metric="success_rate"`` Table 6, from the results that carry a success rate).

    ``<task>@<frames>.json`` files (earlier snapshots) are not part of the table; with
    ``every_snapshot`` they are read too (the budget curves, :mod:`dvfb.analysis.budget`), each
    score's ``pretrain_frames`` telling its snapshot.
    """
    scores = []
    for run in runs:
        results = (run.run.snapshot_zeroshot_results(AnalysisError) if every_snapshot
                   else run.run.zeroshot_results(AnalysisError))
        for path, result in results:
            value = getattr(result, metric)
            if value is None:
                continue
            scores.append(Score("zeroshot", run.method, run.config.domain, result.task, run.config.seed,
                                _number(path, {metric: value}, metric), path, episodes=_episodes(result.returns),
                                pretrain_frames=result.snapshot_frames))
    return scores


def finetune_scores(runs: Iterable[FinetuneEntry], metric: str = RETURN) -> list[Score]:
    """The last point of each fine-tuning curve ``RUN/finetune/<name>/curve.json`` (paper Table 2),
    or its success rate (``metric="success_rate"``, points that carry one)."""
    scores = []
    for run in runs:
        curve = run.run.curve(AnalysisError)
        if curve is None:
            log.warning("%s has no curve.json yet; skipped", run.path)
            continue
        path = run.run.curve_path
        if not curve.curve:
            raise AnalysisError(f"{path}: 'curve' is missing or empty")
        last = curve.curve[-1]
        if not _has(last, metric):
            continue
        scores.append(Score("finetune", run.method, run.config.domain, run.config.task,
                            (run.pretrain_seed, run.config.seed), _number(path, last, metric), path,
                            frames=int(_number(path, last, "frames")), episodes=_episodes(last.get("returns")),
                            pretrain_frames=run.config.snapshot))
    return scores


def _budgets(scores: Iterable[Score]) -> dict[tuple[str, str], Counter]:
    """The numbers of each (method, domain) by the frames of the pre-training snapshot behind them."""
    budgets: dict[tuple[str, str], Counter] = {}
    for score in scores:
        if score.pretrain_frames is not None:
            budgets.setdefault((score.method, score.domain), Counter())[score.pretrain_frames] += 1
    return budgets


def split_budgets(scores: Sequence[Score]) -> list[Score]:
    """``scores`` with the method of each number relabelled by its pre-training budget
    (:func:`budget_label`) where one method has numbers of several budgets on one domain: a table
    cell never averages a 1,200-frame and a 100,000-frame pre-training (the paper keeps budgets
    apart). Where a method has one budget its label is unchanged."""
    mixed = {key for key, counts in _budgets(scores).items() if len(counts) > 1}
    return [replace(s, method=budget_label(s.method, s.pretrain_frames))
            if (s.method, s.domain) in mixed else s for s in scores]


def mixed_pretraining_notes(scores: Iterable[Score], table: str) -> list[str]:
    """One note per method and domain whose numbers in ``table`` (``scores`` before
    :func:`split_budgets`) come from pre-training snapshots of different frames: the columns they
    are in."""
    return [f"{table}: {method} on {domain} has runs of different pre-training budgets, each budget its own column ("
            + ", ".join(f"{budget_label(method, f)}: {n} number(s)" for f, n in sorted(counts.items()))
            + "); evaluate one snapshot (--snapshot) to compare like with like"
            for (method, domain), counts in sorted(_budgets(scores).items()) if len(counts) > 1]


def random_scores(files: Iterable[str | os.PathLike], metric: str = RETURN) -> list[Score]:
    """Scores of ``dvfb random-policy --output`` files; each file is one seed of the column."""
    scores = []
    for raw in files:
        path = Path(raw)
        if not path.is_file():
            raise AnalysisError(f"random-policy file {path} does not exist")
        data = read_json_object(path)
        tasks = data.get("tasks")
        if not isinstance(tasks, dict) or "domain" not in data:
            raise AnalysisError(f"{path} is not a random-policy file (written by `dvfb random-policy --output`)")
        for task, result in sorted(tasks.items()):
            if not isinstance(result, dict):
                raise AnalysisError(f"{path}: tasks.{task} is not an object")
            if not _has(result, metric):
                continue
            scores.append(Score("random", "random", data["domain"], task, data.get("seed", 0),
                                _number(path, result, metric), path, episodes=_episodes(result.get("returns"))))
    return scores


def check_duplicates(scores: Iterable[Score]) -> None:
    """Two files with the same (kind, method, seed, task) are an error naming both."""
    first: dict[tuple, Path] = {}
    for score in scores:
        key = (score.kind, score.method, score.seed, score.task)
        if key in first and first[key] != score.source:
            seed = score.seed
            if isinstance(seed, tuple):
                seed = f"pretrain seed {seed[0]}, fine-tuning seed {seed[1]}"
            raise AnalysisError(
                f"duplicate {score.kind} result for method {score.method!r}, seed {seed}, task "
                f"{score.task!r}: {first[key]} and {score.source}; pass only one of them")
        first.setdefault(key, score.source)


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf floats replaced by None, so the JSON written is strict JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value
