"""The sweep description and its cells (README "Sweeps", docs/sweeps.md).

A sweep is one :class:`SweepConfig`: methods x domains x seeds, the phases to run, and
``overrides``, the pre-training config flags of every cell. An override with one value applies to
every cell of a method that has the option; one with several values is a grid axis, e.g.
``{"exploration.alpha": [1, 5, 50]}`` (on the command line ``--exploration.alpha 1,5,50``).
An axis applies only to the methods that have its section: FB cells do not multiply over
``exploration.alpha``.

Each combination is a :class:`Cell`, named from its values
(``dvfb_walker_exploration.alpha=5.0_s0``) and run in ``SWEEP/runs/<name>/``.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dvfb import envs
from dvfb.agents import agent_names, get_spec
from dvfb.core.config import (SEED_MAX, canonical_key, field_type, flag_name, format_value, from_dict, is_list_type,
                              merge, param, parse_text, to_dict)
from dvfb.core.errors import ConfigError
from dvfb.runs import read_json
from dvfb.runs.presets import preset_config
from dvfb.runs.run_config import run_config_class

PHASES = ("pretrain", "zeroshot", "finetune")
EXECUTORS = ("local", "slurm", "debug")
# Pre-training fields that the sweep sets per cell (agents, domains, seeds, preset) or per
# executor (torch threads), so they are not overrides.
CELL_FIELDS = ("agent", "domain", "seed", "preset", "torch_threads")
# The fields that define what a sweep computes; a re-run into the same directory must match them.
# Executor fields may change between runs (start locally, continue on SLURM).
GRID_FIELDS = ("agents", "domains", "seeds", "preset", "phases", "zeroshot_tasks", "zeroshot_snapshots",
               "finetune_tasks", "exclude", "overrides")
SWEEP_FILE = "sweep.json"


@dataclass
class Resources:
    """What one SLURM job of a phase asks for."""

    cpus: int = param(1, "CPUs per job (--cpus-per-task); the phase runs torch with this many threads.")
    gpus: int = param(0, "GPUs per job (--gpus-per-node); with --device auto (the default) the phase uses CUDA.")
    mem_gb: float = param(4.0, "Memory per job in GB (--mem).")
    time_min: int = param(1440, "Time limit in minutes (--time). Before it, the job gets USR2, stops its phase "
                                "and requeues itself; the phase resumes from its checkpoint.")


@dataclass
class SlurmConfig:
    """The slurm executor: job arrays through submitit, one array per phase."""

    partition: str | None = param(None, "Partition (--partition); none: the cluster's default.")
    account: str | None = param(None, "Account (--account).")
    qos: str | None = param(None, "Quality of service (--qos).")
    array_parallelism: int = param(32, "Jobs of one array that run at once (the limit of sbatch --array).")
    extra_sbatch: list[str] = param([], "Further #SBATCH options, e.g. --constraint=a100 --exclude=node7.")
    setup: list[str] = param([], "Shell lines run in each job before the phase (module load ..., source ...).")
    python: str | None = param(None, "Python interpreter on the compute nodes; none: the one running dvfb sweep.")
    signal_delay_s: int = param(120, "Seconds before the time limit at which SLURM sends USR2.")
    max_requeues: int = param(10, "Times a job may requeue itself after a time-out.")
    poll_s: float = param(10.0, "Seconds between two looks at squeue while the sweep runs.")
    pretrain: Resources = field(default_factory=lambda: Resources(cpus=1, mem_gb=8.0, time_min=1440),
                                metadata={"help": "Resources of a pre-training job."})
    zeroshot: Resources = field(default_factory=lambda: Resources(cpus=1, mem_gb=4.0, time_min=240),
                                metadata={"help": "Resources of a zero-shot job (every task of the cell)."})
    finetune: Resources = field(default_factory=lambda: Resources(cpus=1, mem_gb=8.0, time_min=1440),
                                metadata={"help": "Resources of a fine-tuning job (one task)."})


@dataclass
class SweepConfig:
    """A sweep: the grid, the phases, and how it is executed."""

    agents: list[str] = param(["dvfb", "fb"], "Methods (dvfb agents).")
    domains: list[str] = param(["walker"], "Domains (dvfb tasks).")
    seeds: list[int] = param([0, 1, 2], "Seeds.", at_least=0, at_most=SEED_MAX)
    preset: str = param("small", "Base configuration of every cell.", ("small", "paper", "code"))
    phases: list[str] = param(["pretrain", "zeroshot"], "Phases: pretrain, zeroshot, finetune (pretrain always).")
    zeroshot_tasks: list[str] = param(["all"], "Zero-shot tasks; all = every task of the cell's domain.")
    zeroshot_snapshots: list[int] = param([], "Earlier snapshots (their frames) that are evaluated zero-shot too, "
                                              "besides the final one; each must be among the cells' "
                                              "snapshot_frames (an override).", at_least=1)
    finetune_tasks: list[str] = param([], "Fine-tuning tasks (all = every task of the domain).")
    overrides: dict[str, list] = param({}, "Pre-training config options of the cells, as lists of values; "
                                           "several values make a grid axis.")
    exclude: list[str] = param([], "Cells left out of the grid, as shell-style patterns of their names (e.g. "
                                   "rnd_point_mass_maze_* for a method on one domain only, supervised_*_s2 for "
                                   "fewer seeds of one method); each must match a cell.")
    executor: str = param("local", "Where phases run: local worker processes, slurm jobs, or debug "
                                   "(in this process, one after the other).", EXECUTORS)
    workers: int = param(0, "local: phases that run at once; 0 = the number of cores.")
    torch_threads: int = param(0, "torch threads per phase; 0 = cores / workers (local), the job's CPUs (slurm), "
                                  "torch's default (debug).")
    seeds_per_job: int = param(1, "Seeds of a cell that run as one group, each phase in one process and one job "
                                  "(dvfb pretrain --seeds, then zero-shot and fine-tuning of the group's runs, "
                                  "docs/members.md); 1 = a process per seed.", at_least=1)
    report: bool = param(True, "Write SWEEP/report (dvfb report, ± over seeds) when every cell is done.")
    slurm: SlurmConfig = field(default_factory=SlurmConfig, metadata={"help": "The slurm executor."})


@dataclass(frozen=True)
class Cell:
    """One point of the grid: a method on a domain with a seed and its override values."""

    name: str
    agent: str
    domain: str
    seed: int
    values: tuple[tuple[str, Any], ...]  # every override that applies to the method
    axes: tuple[str, ...]  # the keys of ``values`` that are swept (part of the name)

    def overrides(self) -> dict:
        """The override values as the nested dict that :func:`dvfb.core.config.merge` takes."""
        nested: dict = {}
        for key, value in self.values:
            *sections, name = key.split(".")
            target = nested
            for section in sections:
                target = target.setdefault(section, {})
            target[name] = value
        return nested


# ---------------------------------------------------------------------------------------------
# option keys and values


def _name_part(value: Any) -> str:
    # One safe path component: keep what shells and file systems take as is.
    return re.sub(r"[^A-Za-z0-9_.+\-]", "-", format_value(value).replace(",", "-"))


# ---------------------------------------------------------------------------------------------
# building and checking a sweep


def _run_config_class(agent: str) -> type:

    if agent not in agent_names():
        raise ConfigError(f"unknown agent {agent!r}; choose from {', '.join(agent_names())}")
    return run_config_class(agent)


def normalise_overrides(config: SweepConfig, raw: dict[str, Any], from_text: bool) -> dict[str, list]:
    """Overrides as ``{dotted key: [values]}`` with typed values.

    ``raw`` comes from a file (typed values; a list is an axis, except for list-typed options,
    where a list of lists is) or from the command line (``from_text``: comma-separated text, an
    axis unless the option is list-typed).
    """

    classes = [_run_config_class(agent) for agent in config.agents]
    task_fields = {get_spec(agent).task_field for agent in config.agents} - {None}
    out: dict[str, list] = {}
    for given_key, value in _flat(raw).items():
        key = canonical_key(given_key)
        if key in task_fields:
            raise ConfigError(f"{flag_name(key)} is set by the sweep itself: a supervised cell per zero-shot task")
        if key.split(".")[0] in CELL_FIELDS:
            raise ConfigError(f"{flag_name(key)} is set by the sweep itself; use its agents, domains, seeds, "
                              "preset or torch_threads")
        tp = next((t for t in (field_type(c, key) for c in classes) if t is not None), None)
        if tp is None:
            raise ConfigError(f"no method of the sweep ({', '.join(config.agents)}) has the option {flag_name(key)}")
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            raise ConfigError(f"{flag_name(key)} is a section of options, not an option; give its options, "
                              f"e.g. {flag_name(key + '.' + dataclasses.fields(tp)[0].name)}")
        if not from_text and is_list_type(tp) and value is not None and not isinstance(value, list):
            raise ConfigError(f"{flag_name(key)} takes a list of values (a list of lists is a grid axis), "
                              f"got {value!r}")
        if from_text:
            texts = [str(value)] if is_list_type(tp) else str(value).split(",")
            values = [parse_text(key, tp, text) for text in texts]
        elif is_list_type(tp):
            values = list(value) if value and all(isinstance(v, list) for v in value) else [value]
        else:
            values = list(value) if isinstance(value, list) else [value]
        if not values:
            raise ConfigError(f"{flag_name(key)} has no value")
        if len({json.dumps(v) for v in values}) != len(values):
            raise ConfigError(f"{flag_name(key)} lists a value twice: {values}")
        out[key] = values
    return out


def _flat(raw: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A file's overrides with nested tables (TOML's ``[overrides.fb]``) as dotted keys."""
    flat: dict[str, Any] = {}
    for key, value in raw.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _tasks(config: SweepConfig, domain: str, requested: list[str]) -> list[str]:

    if requested == ["all"]:
        return list(envs.tasks_of_domain(domain))
    return [t for t in requested if t in envs.tasks_of_domain(domain)]


def zeroshot_tasks(config: SweepConfig, cell: Cell) -> list[str]:
    """The cell's evaluation tasks; a supervised cell is evaluated on its own task."""
    if "zeroshot" not in config.phases:
        return []
    task = cell_task(cell)
    return [task] if task is not None else _tasks(config, cell.domain, config.zeroshot_tasks)


def finetune_tasks(config: SweepConfig, cell: Cell) -> list[str]:
    """The cell's fine-tuning tasks; none for a supervised cell (it trained on its task already)."""
    if "finetune" not in config.phases or cell_task(cell) is not None:
        return []
    return _tasks(config, cell.domain, config.finetune_tasks)


def check(config: SweepConfig) -> None:
    """Everything about a sweep that can be checked before anything runs (bad input: ConfigError)."""

    for name, values in (("agents", config.agents), ("domains", config.domains), ("seeds", config.seeds)):
        if not values:
            raise ConfigError(f"the sweep has no {name}")
        if len(set(values)) != len(values):
            raise ConfigError(f"{name} lists a value twice: {values}")
    for agent in config.agents:
        _run_config_class(agent)
    for domain in config.domains:
        envs.check_domain(domain)  # unknown, or its extra missing: before any job starts
    unknown = [p for p in config.phases if p not in PHASES]
    if unknown:
        raise ConfigError(f"unknown phase(s) {', '.join(unknown)}; choose from {', '.join(PHASES)}")
    if "pretrain" not in config.phases:
        raise ConfigError("the phases must include pretrain (zero-shot and fine-tuning start from it)")
    all_tasks = {t for d in config.domains for t in envs.tasks_of_domain(d)}
    for what, tasks in (("zeroshot_tasks", config.zeroshot_tasks), ("finetune_tasks", config.finetune_tasks)):
        if tasks == ["all"]:
            continue
        stray = [t for t in tasks if t not in all_tasks]
        if stray:
            raise ConfigError(f"{what}: {', '.join(stray)} is not a task of {', '.join(config.domains)} (dvfb tasks)")
    if "finetune" in config.phases and not config.finetune_tasks:
        raise ConfigError("the finetune phase needs finetune_tasks (--finetune-tasks TASK ...)")
    if config.zeroshot_snapshots and "zeroshot" not in config.phases:
        raise ConfigError("zeroshot_snapshots needs the zeroshot phase")
    if len(set(config.zeroshot_snapshots)) != len(config.zeroshot_snapshots):
        raise ConfigError(f"zeroshot_snapshots lists a value twice: {config.zeroshot_snapshots}")
    every = _grid(config)
    for pattern in config.exclude:
        if not any(fnmatch.fnmatchcase(cell.name, pattern) for cell in every):
            raise ConfigError(f"exclude: {pattern!r} matches no cell of the sweep (dvfb sweep run --dry-run lists them)")
    if not cells(config):
        raise ConfigError("exclude leaves the sweep without cells")
    if config.workers < 0 or config.torch_threads < 0:
        raise ConfigError("workers and torch_threads must be >= 0")
    if config.slurm.array_parallelism < 1:
        raise ConfigError("slurm.array_parallelism must be >= 1")
    names = [cell.name for cell in cells(config)]
    if len(set(names)) != len(names):
        raise ConfigError("two cells of the sweep get the same name; give the swept values distinct texts")
    for cell in cells(config):
        run = cell_config(config, cell)  # every cell's config must be valid
        for frames in config.zeroshot_snapshots:
            if frames >= run.frames or frames not in run.snapshot_frames:
                raise ConfigError(f"zeroshot_snapshots: cell {cell.name} keeps no snapshot after {frames} frames before "
                                  f"its last ({run.frames}); add it to --snapshot-frames (now "
                                  f"{format_value(run.snapshot_frames) or 'none'})")


def cells(config: SweepConfig) -> list[Cell]:
    """The grid, in the order agents, domains, swept values, seeds, without the excluded cells."""
    return [cell for cell in _grid(config)
            if not any(fnmatch.fnmatchcase(cell.name, pattern) for pattern in config.exclude)]


def matching(config: SweepConfig, patterns: list[str]) -> list[Cell]:
    """The sweep's cells whose names match one of ``patterns`` (shell-style); each pattern must match one."""
    every = cells(config)
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(cell.name, pattern) for cell in every):
            raise ConfigError(f"--only {pattern!r} matches no cell of the sweep (dvfb sweep run --dry-run lists them)")
    return [cell for cell in every if any(fnmatch.fnmatchcase(cell.name, p) for p in patterns)]


def _grid(config: SweepConfig) -> list[Cell]:
    """Every combination of agents, domains, swept values and seeds."""
    out = []
    for agent in config.agents:
        cls = _run_config_class(agent)
        keys = [k for k in config.overrides if field_type(cls, k) is not None]
        axes = tuple(k for k in keys if len(config.overrides[k]) > 1)
        task_field = get_spec(agent).task_field
        for domain in config.domains:
            # A method that learns one task's reward (the supervised reference) gets a cell per
            # task: the zero-shot tasks of the sweep, each trained with the cells' budget.
            tasks = _tasks(config, domain, config.zeroshot_tasks) if task_field is not None else [None]
            for task in tasks:
                own = ((task_field, task),) if task is not None else ()
                place = task if task is not None else domain
                for combination in itertools.product(*(config.overrides[k] for k in keys)):
                    values = tuple(zip(keys, combination)) + own
                    swept = "".join(f"_{k}={_name_part(v)}" for k, v in values if k in axes)
                    for seed in config.seeds:
                        out.append(Cell(f"{agent}_{place}{swept}_s{seed}", agent, domain, seed, values, axes))
    return out


def job_groups(config: SweepConfig) -> list[list[Cell]]:
    """The cells that run as one group (``seeds_per_job`` seeds of a cell that differ
    only in their seed, in the sweep's seed order); the first of each is its leader."""
    groups: dict[tuple, list[list[Cell]]] = {}
    order: list[tuple] = []
    for cell in cells(config):
        key = (cell.agent, cell.domain, cell.values)
        if key not in groups:
            groups[key] = [[]]
            order.append(key)
        if len(groups[key][-1]) == config.seeds_per_job:
            groups[key].append([])
        groups[key][-1].append(cell)
    return [group for key in order for group in groups[key]]


SEED_SUFFIX = "_s{seed}"


def group_run_template(cell: Cell) -> str:
    """A cell's run-directory name with its seed as ``{seed}`` (what ``dvfb pretrain --seeds`` fills in)."""
    own = f"_s{cell.seed}"
    return cell.name[: -len(own)] + SEED_SUFFIX


def cell_task(cell: Cell) -> str | None:
    """The task a cell's method learns from (the supervised reference), or None."""

    field_name = get_spec(cell.agent).task_field
    return dict(cell.values).get(field_name) if field_name is not None else None


def cell_config(config: SweepConfig, cell: Cell):
    """The cell's full pre-training config (what ``dvfb pretrain`` would resolve)."""

    base = preset_config(config.preset, cell.agent, domain=cell.domain, seed=cell.seed)
    try:
        return merge(base, cell.overrides())
    except ConfigError as exc:
        raise ConfigError(f"cell {cell.name}: {exc}") from exc


def pretrain_flags(cell: Cell) -> list[str]:
    """The override flags of the cell for ``dvfb pretrain``; a list value is one argument per item,
    as the command's list options take them (``--snapshot-frames 25000 50000``)."""
    flags: list[str] = []
    for key, value in cell.values:
        if isinstance(value, (list, tuple)):
            flags += [flag_name(key), *(format_value(item) for item in value)]
        else:
            flags += [flag_name(key), format_value(value)]
    return flags


# ---------------------------------------------------------------------------------------------
# reading and saving


def read_file(path: Path) -> dict:
    """The contents of a sweep file (``.toml`` or ``.json``)."""
    if not path.is_file():
        raise ConfigError(f"sweep file {path} does not exist")
    if path.suffix not in (".toml", ".json"):
        raise ConfigError(f"sweep file {path}: expected a .toml or .json file")
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"sweep file {path} cannot be read: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"sweep file {path} must hold an object of sweep fields (agents, seeds, ...), "
                          f"not a {type(data).__name__}")
    return data


def build(base: dict, file_data: dict, flag_data: dict, flag_overrides: dict[str, str]) -> SweepConfig:
    """Defaults <- ``base`` (a stored sweep) <- a sweep file <- command-line flags, checked.

    ``flag_overrides`` are the config flags typed on the command line (text values).
    """
    file_data = dict(file_data)
    raw_file_overrides = file_data.pop("overrides", {})
    if not isinstance(raw_file_overrides, dict):
        raise ConfigError("overrides must be a table of option = value(s)")
    data = to_dict(SweepConfig())
    for layer in (base, file_data, flag_data):
        config = merge(from_dict(SweepConfig, data), layer)
        data = to_dict(config)
    config = from_dict(SweepConfig, data)
    overrides = dict(config.overrides)  # stored (canonical) overrides of ``base``
    overrides.update(normalise_overrides(config, raw_file_overrides, from_text=False))
    overrides.update(normalise_overrides(config, flag_overrides, from_text=True))
    config = dataclasses.replace(config, overrides=overrides)
    check(config)
    return config


def same_grid(a: SweepConfig, b: SweepConfig) -> list[str]:
    """The grid fields in which two sweeps differ."""
    da, db = to_dict(a), to_dict(b)
    return [k for k in GRID_FIELDS if json.dumps(da[k], sort_keys=True) != json.dumps(db[k], sort_keys=True)]


def load_stored(path: Path) -> SweepConfig:
    """The sweep saved in a sweep directory."""

    data = read_json(path / SWEEP_FILE, error=ConfigError)
    try:
        return from_dict(SweepConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{path / SWEEP_FILE}: {exc}") from exc
