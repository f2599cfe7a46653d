"""Starting or continuing a sweep, its reports, and ``dvfb sweep status`` (README "Sweeps",
docs/sweeps.md)."""

from __future__ import annotations

import itertools
import json
import os
import socket
import time
from pathlib import Path

from dvfb.analysis import bands
from dvfb.analysis.common import AnalysisError
from dvfb.analysis.report import make_report
from dvfb.core.config import format_value, to_dict
from dvfb.core.errors import ConfigError, DvfbError
from dvfb.runs import LOCK_FILE, RunLock, last_metric_record, read_json, recent_rate, write_json_atomic
from dvfb.runs.layout import PretrainRun
from dvfb.runs.machine import cores
from dvfb.sweep import spec
from dvfb.sweep.executors import EXECUTORS, Outcome, SlurmError, _sbatch_options, alive_jobs
from dvfb.sweep.spec import Cell, SweepConfig
from dvfb.sweep.units import (KEPT_FILES, SweepDir, command, group_of, is_done, jobs_of, mark_failed,
                              pretrain_target, read_state, units_of)


# What a sweep directory keeps out of git: everything but the small result files (configs,
# summaries, zero-shot results, curves, metric records), so that a committed sweep directory is its
# results and the sweep, run again from a clone, runs only what is missing (docs/sweeps.md).
GITIGNORE = """\
# Written by dvfb sweep: what git leaves out of this sweep directory (docs/sweeps.md, "Keeping the
# results"). The configs, summaries, zero-shot results, curves and metric records stay, so that
# the sweep, run again from a clone, runs only what is missing.
checkpoints/
snapshots/
tb/
wandb/
analysis/
state/
logs/
slurm/
jobs.json
.lock
"""


def prepare(path: Path, requested: SweepConfig) -> SweepDir:
    """Save a new sweep into ``path``, or check that ``path`` holds the same sweep (a re-run).

    A different grid in an existing sweep directory is an error and changes nothing.
    """
    sweep = SweepDir(path)
    if sweep.config_path.exists():
        check_same_grid(sweep, requested)
    else:
        check_new_sweep_dir(path)
    write_json_atomic(sweep.config_path, spec.to_dict(requested))
    if not sweep.gitignore_path.exists():
        sweep.gitignore_path.write_text(GITIGNORE, encoding="utf-8")
    return sweep


def check_same_grid(sweep: SweepDir, requested: SweepConfig) -> None:
    """A re-run must ask for the grid its directory holds (the executor settings may differ), or
    for a grid that grows it: one that keeps every stored cell with the same config and units and
    adds cells or units (a domain, a method, a seed, a task added to a study). A grown grid says so
    in one line; anything else is refused and changes nothing (docs/sweeps.md, "Growing a sweep")."""
    stored = spec.load_stored(sweep.path)
    differ = spec.same_grid(stored, requested)
    if not differ:
        return
    problem = _not_grown(stored, requested)
    if problem is not None:
        raise ConfigError(f"{sweep.path} holds another sweep ({', '.join(differ)} differ from {sweep.config_path}; "
                          f"{problem}); choose another --dir, or repeat the original command to continue it")
    old = {cell.name for cell in spec.cells(stored)}
    added = [cell.name for cell in spec.cells(requested) if cell.name not in old]
    print(f"[sweep] the grid grows: {len(added)} new cell(s) beside the {len(old)} of {sweep.config_path} "
          f"({', '.join(differ)} extended); the stored cells keep their results")


def _not_grown(stored: SweepConfig, requested: SweepConfig) -> str | None:
    """Why ``requested`` does not grow ``stored`` (a stored cell missing, or with another config or
    fewer units), or None when it does."""
    if requested.preset != stored.preset:
        return "another preset"
    new = {cell.name: cell for cell in spec.cells(requested)}
    for cell in spec.cells(stored):
        if cell.name not in new:
            return f"cell {cell.name} is not in the new grid"
        if to_dict(spec.cell_config(stored, cell)) != to_dict(spec.cell_config(requested, new[cell.name])):
            return f"cell {cell.name} would get another config"
        kept = {unit.name for unit in units_of(requested, new[cell.name])}
        lost = [unit.name for unit in units_of(stored, cell) if unit.name not in kept]
        if lost:
            return f"cell {cell.name} would lose its unit(s) {', '.join(lost)}"
    return None


def check_new_sweep_dir(path: Path) -> None:
    """A sweep starts in a new or empty directory (its own lock file aside), never in a file or in
    another directory's contents."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"--dir {path} is a file; give a directory for the sweep")
    if (path.exists() and not (path / spec.SWEEP_FILE).exists()
            and any(p.name not in (LOCK_FILE, *KEPT_FILES) for p in path.iterdir())):
        raise ConfigError(f"{path} exists and is not a sweep directory (no {spec.SWEEP_FILE}); choose another --dir")


def run(path: Path, config: SweepConfig, only: list[str] | None = None) -> Outcome:
    """Run every unit of the sweep that is not done yet, then write the reports. With ``only``
    (shell-style patterns of cell names), run only those cells' units this time; the others wait
    for a later run, and the reports wait until every cell is done.

    One sweep process per directory (the run directories' lock, on the sweep directory): a second
    one is refused naming the first's process id, before it reads or writes any state.
    """
    check_new_sweep_dir(path)  # before the lock file is written into it
    chosen = spec.matching(config, only) if only else None
    lock = RunLock(path)
    with lock:
        try:
            sweep = prepare(path, config)
        except BaseException:
            lock.remove_if_created()
            raise
        close_dead_units(sweep, config)
        outcome = EXECUTORS[config.executor](sweep, config, chosen)
        if config.report:
            left = [cell.name for cell in spec.cells(config) if not all(is_done(sweep, config, u)
                                                                        for u in units_of(config, cell))]
            if chosen is not None and left:
                print(f"[sweep] no report yet: {len(left)} cell(s) of the sweep are not done (--only)")
            else:
                write_reports(sweep, config)
        return outcome


def dry_run(path: Path, config: SweepConfig, only: list[str] | None = None) -> list[str]:
    """What ``dvfb sweep run --dry-run`` prints: the cells, the jobs and the units a run would start,
    after the checks of a real run (every cell's config, built by :func:`dvfb.sweep.spec.build`;
    the sweep directory; a stored grid; the slurm executor's extra options). Nothing is created,
    written or submitted, and SLURM is not asked (docs/sweeps.md, docs/reproduce.md)."""
    check_new_sweep_dir(path)
    sweep = SweepDir(path)
    if sweep.config_path.is_file():
        check_same_grid(sweep, config)
    if config.executor == "slurm":
        try:
            _sbatch_options(config.slurm.extra_sbatch)
        except (DvfbError, ValueError) as exc:  # ValueError: shlex's unbalanced quotes
            raise ConfigError(f"slurm.extra_sbatch: {exc}") from exc
    chosen = spec.matching(config, only) if only else None
    cells = spec.cells(config)
    jobs = jobs_of(config, chosen)
    state = "continues the sweep in" if sweep.config_path.is_file() else "would create"
    lines = [f"dry run: nothing is created, run or submitted; a run {state} {path}",
             f"{len(cells)} cell(s): agents {', '.join(config.agents)}; domains {', '.join(config.domains)}; "
             f"seeds {', '.join(map(str, config.seeds))}; preset {config.preset}; phases {', '.join(config.phases)}"]
    rows = [("cell", "frames", "units")]
    for cell in cells:
        units = []
        for unit in units_of(config, cell):
            text = unit.name
            if unit.phase == "zeroshot" and unit.snapshot is None:
                text += f" ({len(spec.zeroshot_tasks(config, cell))} tasks)"
            units.append(text)
        rows.append((cell.name, f"{spec.cell_config(config, cell).frames:,}", ", ".join(units)))
    widths = [max(len(row[i]) for row in rows) for i in range(2)]
    lines += ["  " + f"{a.ljust(widths[0])}  {b.rjust(widths[1])}  {c}" for a, b, c in rows]
    units = [unit for first, rest in jobs for unit in (first, *rest)]
    todo = [unit for unit in units if not is_done(sweep, config, unit)]
    per_phase = {phase: sum(u.phase == phase for u in todo) for phase in spec.PHASES}
    if chosen is not None:
        lines.append(f"--only: this run takes {len(jobs)} of the sweep's {len(jobs_of(config))} pre-training "
                     "process(es) and their units")
    lines.append(f"{len(jobs)} pre-training process(es) of {config.seeds_per_job} seed(s) at most; "
                 f"{len(units)} unit(s), {len(todo)} to run (" + ", ".join(f"{n} {p}" for p, n in per_phase.items())
                 + f"), {len(units) - len(todo)} already done; executor {config.executor}")
    if config.executor == "slurm":
        s = config.slurm
        where = ", ".join(f"{name} {getattr(s, name)}" for name in ("partition", "account", "qos")
                          if getattr(s, name) is not None) or "the cluster's default partition"
        lines.append(f"slurm: {where}; one job array per phase, {s.array_parallelism} job(s) at once")
        for phase in spec.PHASES:
            if phase in config.phases:
                r: spec.Resources = getattr(s, phase)
                lines.append(f"  {phase} jobs: {r.gpus} GPU(s), {r.cpus} CPU(s), {r.mem_gb:g} GB, {r.time_min} min")
        threads = config.torch_threads or s.pretrain.cpus
    elif config.executor == "local":
        threads = config.torch_threads or max(1, cores() // min(config.workers or cores(), cores()))
    else:
        threads = config.torch_threads
    lines.append("pre-training commands:")
    lines += [f"  dvfb {' '.join(command(sweep, config, first, threads))}" for first, _ in jobs
              if not is_done(sweep, config, first)]
    return lines


def close_dead_units(sweep: SweepDir, config: SweepConfig) -> list[str]:
    """Units whose state says running but whose process on this host is gone (a killed local
    sweep): recorded as failed with that reason, so that no state stays running after its
    process; the executor then runs them again."""
    closed = []
    for cell in spec.cells(config):
        for unit in units_of(config, cell):
            state = read_state(sweep, unit) or {}
            if state.get("state") == "running" and not state.get("job_id") and _alive(state, None) is None \
                    and state.get("host") == socket.gethostname():
                mark_failed(sweep, unit, "its process ended without recording how (the sweep was killed?)")
                closed.append(unit.key)
    return closed


def report_groups(config: SweepConfig) -> dict[str, list[Cell]]:
    """The cells of each report: one report per combination of swept values (a method without
    a swept option is in every report), all cells in one report when nothing is swept."""
    cells = spec.cells(config)
    axes = [k for k, values in config.overrides.items() if len(values) > 1]
    if not axes:
        return {"": cells}
    groups = {}
    for combination in itertools.product(*(config.overrides[k] for k in axes)):
        chosen = dict(zip(axes, combination))
        name = "_".join(f"{k}={format_value(v)}" for k, v in chosen.items())
        groups[name] = [c for c in cells
                        if all(json.dumps(dict(c.values)[k]) == json.dumps(v) for k, v in chosen.items() if k in c.axes)]
    return groups


def write_reports(sweep: SweepDir, config: SweepConfig) -> list[Path]:
    """``dvfb report`` over the seeds of each group (:func:`report_groups`) into SWEEP/report/.
    The report is derived from the runs, so it is rewritten on every run of the sweep."""

    written = []
    for name, cells in report_groups(config).items():
        runs = [sweep.run_path(c) for c in cells if sweep.run_path(c).is_dir()]
        if not runs:
            continue
        out = sweep.report_dir / name if name else sweep.report_dir
        try:
            report = make_report(runs, out, overwrite=True)
        except AnalysisError as exc:  # no results yet (every cell failed): nothing to report
            print(f"[sweep] no report for {name or 'the sweep'}: {exc}")
            continue
        written.append(report.out_dir / "report.md")
        print(f"[sweep] report: {report.out_dir / 'report.md'}")
    return written


# ---------------------------------------------------------------------------------------------
# status


def _last_train_record(run: Path) -> dict:
    """The newest complete training record of a run; {} when none (a status only reports)."""
    try:
        return last_metric_record(run, "train") or {}
    except (OSError, DvfbError):
        return {}


def _alive(state: dict, jobs: dict[str, str] | None) -> str | None:
    """'running' or 'queued' when the unit's process or job is alive, else None."""
    job = state.get("job_id")
    if job and jobs is not None:
        squeue_state = jobs.get(job)
        return None if squeue_state is None else ("running" if squeue_state == "RUNNING" else "queued")
    if state.get("host") == socket.gethostname() and state.get("pid"):
        try:
            os.kill(int(state["pid"]), 0)
        except (ProcessLookupError, PermissionError):
            return None
        return "running"
    return None


def _format_seconds(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


def cell_status(sweep: SweepDir, config: SweepConfig, cell: Cell, jobs: dict[str, str] | None,
                recorded: dict[str, str], sweep_active: bool = False, reference: bands.Bands | None = None) -> dict:
    """State (done / running / queued / failed / stopped), frames, ETA, the health of its newest
    evaluation while pre-training against ``reference`` (docs/health.md; default: the package's
    bands) and a note of one cell."""
    units = units_of(config, cell)
    states = {u.name: read_state(sweep, u) or {} for u in units}
    leader = group_of(config, cell)[0]
    if leader != cell:  # its phases run in its group leader's units (seeds_per_job)
        states = {u.name: read_state(sweep, u) or {} for u in units_of(config, leader)}
    done = [is_done(sweep, config, u) for u in units]
    target = pretrain_target(config, cell)
    record = _last_train_record(sweep.run_path(cell))
    frames = target if done[0] else int(record.get("step", 0))
    live = {u.name: _alive(states[u.name], jobs) for u in units if states[u.name].get("state") == "running"}
    keys = {u.name: u.key for u in units_of(config, leader)}  # where a unit's job is recorded
    queued = [u for u in units if jobs is not None and recorded.get(keys[u.name]) in jobs
              and jobs[recorded[keys[u.name]]] != "RUNNING" and not is_done(sweep, config, u)]
    failed = [u for u, d in zip(units, done) if not d and states[u.name].get("state") == "failed"]
    eta = ""
    if all(done):
        state, note = "done", ""
    elif "running" in live.values():
        state = "running"
        running = [name for name, alive in live.items() if alive == "running"]
        note = ", ".join(running)
        rate = recent_rate(record)  # of the last logging interval: an average since the start hides a slowdown
        if "pretrain" in running and rate:
            eta = _format_seconds((target - frames) / rate)
    elif failed:
        state = "failed"
        first = states[failed[0].name]
        note = f"{failed[0].name}: {first.get('reason')} (log: {first.get('log')})"
    elif queued or "queued" in live.values():
        state, note = "queued", ""
    elif any(not d and states[u.name].get("state") in ("interrupted", "running") for u, d in zip(units, done)):
        # A unit that was stopped, or whose process is gone while its state says running.
        state = "stopped"
        note = "interrupted; run the sweep command again to continue"
    else:
        # Units never started: waiting behind others while a sweep process runs, or for one.
        state = "queued"
        note = "" if sweep_active else "not started; run the sweep command to continue"
    phases = f"{sum(done)}/{len(units)}"
    run = sweep.run_path(cell)
    health = bands.summary(bands.run_verdicts(PretrainRun(run, spec.cell_config(config, cell)), reference)) \
        if (run / "metrics" / "eval.jsonl").is_file() else "-"
    return {"cell": cell.name, "state": state, "frames": frames, "target": target, "eta": eta,
            "units_done": phases, "health": health, "note": note}


def status(path: Path) -> tuple[list[dict], str | None]:
    """One row per cell (:func:`cell_status`), and a warning when SLURM jobs cannot be looked up."""
    sweep = SweepDir(path)
    if not sweep.config_path.is_file():
        raise ConfigError(f"{path} is not a sweep directory (no {spec.SWEEP_FILE})")
    config = spec.load_stored(path)
    recorded = read_json(sweep.jobs_path) if sweep.jobs_path.is_file() else {}
    jobs, warning = None, None
    if recorded:
        try:
            jobs = alive_jobs()
        except SlurmError as exc:
            # The files still tell what is done and what failed; only queued/running is unknown.
            warning = f"squeue cannot be asked, so queued and running jobs are not shown: {exc}"
    # A live sweep process (it holds the sweep directory's lock) will start the waiting units;
    # SLURM jobs of a sweep whose submitter was killed are seen through squeue.
    active = RunLock.holder(sweep.path) is not None or bool(jobs)
    reference = bands.load_bands()
    return [cell_status(sweep, config, cell, jobs, recorded, active, reference) for cell in spec.cells(config)], warning


def format_status(rows: list[dict]) -> str:
    header = ("cell", "state", "frames", "ETA", "units done", "health", "note")
    table = [(r["cell"], r["state"], f"{r['frames']}/{r['target']}", r["eta"] or "-", r["units_done"], r["health"],
              r["note"]) for r in rows]
    widths = [max(len(str(row[i])) for row in [header, *table]) for i in range(len(header) - 1)]
    lines = ["  ".join(str(c).ljust(w) for c, w in zip(row[:-1], widths)) + "  " + row[-1] for row in [header, *table]]
    counts = {s: sum(r["state"] == s for r in rows) for s in ("done", "running", "queued", "failed", "stopped")}
    lines.append(", ".join(f"{n} {s}" for s, n in counts.items() if n) + f" ({len(rows)} cells, "
                 f"{time.strftime('%H:%M:%S')})")
    return "\n".join(line.rstrip() for line in lines)
