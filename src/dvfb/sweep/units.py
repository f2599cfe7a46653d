"""One phase of one cell, a *unit*: when it is done, the ``dvfb`` command that runs or resumes it,
and the record of its attempts (README "Sweeps", docs/sweeps.md).

Units: ``pretrain``, ``zeroshot`` (every zero-shot task of the cell, one command, with the final
snapshot), ``zeroshot@<frames>`` (the same with an earlier snapshot, ``zeroshot_snapshots``) and
``finetune-<task>``. A unit runs the ``dvfb`` command line, so a sweep computes exactly what the
commands of the README compute, and resumes the way a user would:

* pre-training is done when ``pretrain_summary.json`` reports the cell's frames; otherwise it
  continues with ``--resume`` from the latest checkpoint, or starts over (``--overwrite``) when it
  was stopped before its first checkpoint;
* zero-shot is done when ``zeroshot/<task>.json`` (``<task>@<frames>.json`` for an earlier
  snapshot) exists for every task; only missing tasks run;
* fine-tuning is done when ``finetune/<task>/finetune_summary.json`` exists, else it resumes or
  starts like pre-training.

With ``seeds_per_job > 1`` the units of a group's leader run for every member of the group
(:func:`grouped`); the other members' units are never run themselves.

A finished unit is never run again, so a re-run rewrites nothing in a finished run. Whether a unit
is done is read from the small result files alone (summaries, zero-shot results), so a sweep
directory committed without its snapshots and checkpoints (the ``.gitignore`` the sweep writes)
is complete again on another machine: only what is missing runs. A zero-shot or fine-tuning unit
that is missing while its cell's snapshot is not there says so instead of training again.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dvfb.core.errors import DvfbError
from dvfb.runs import latest_checkpoint, read_json, write_json_atomic
from dvfb.runs.layout import FinetuneRun, PretrainRun
from dvfb.sweep import spec
from dvfb.sweep.spec import Cell, SweepConfig

# Exit statuses of a phase stopped by a signal (SIGTERM, SIGINT; as a negative returncode or as
# the shell's 128 + n): the unit was interrupted (requeue, preemption, kill), not failed.
_INTERRUPT_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGKILL, signal.SIGHUP)
# How long an interrupted phase may take to write its checkpoint and exit.
STOP_GRACE_S = 60.0


class UnitFailed(DvfbError):
    """A unit's command exited with an error (the reason is the last line of its log)."""


class UnitInterrupted(DvfbError):
    """A unit's command was stopped by a signal; a re-run or requeue continues it."""


# Files a directory may hold before a sweep starts in it (its sweep file and notes, kept beside
# the results it makes): a sweep starts in a new directory or one with only these.
KEPT_FILES = (".gitignore", "README.md", "sweep.toml")


class SweepDir:
    """The paths of a sweep directory (layout in the dvfb.sweep docstring)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    @property
    def gitignore_path(self) -> Path:
        return self.path / ".gitignore"

    @property
    def config_path(self) -> Path:
        return self.path / spec.SWEEP_FILE

    @property
    def runs_dir(self) -> Path:
        return self.path / "runs"

    @property
    def slurm_dir(self) -> Path:
        return self.path / "slurm"

    @property
    def jobs_path(self) -> Path:
        return self.path / "jobs.json"

    @property
    def report_dir(self) -> Path:
        return self.path / "report"

    def run_path(self, cell: Cell) -> Path:
        return self.runs_dir / cell.name

    def state_path(self, unit: Unit) -> Path:
        return self.path / "state" / unit.cell.name / f"{unit.name}.json"

    def log_path(self, unit: Unit) -> Path:
        return self.path / "logs" / unit.cell.name / f"{unit.name}.log"


@dataclass(frozen=True)
class Unit:
    cell: Cell
    phase: str  # pretrain, zeroshot or finetune
    task: str | None = None  # the fine-tuning task
    snapshot: int | None = None  # a zero-shot unit's earlier snapshot (frames); None: the final one

    @property
    def name(self) -> str:
        if self.snapshot is not None:
            return f"{self.phase}@{self.snapshot}"
        return self.phase if self.task is None else f"{self.phase}-{self.task}"

    @property
    def key(self) -> str:
        return f"{self.cell.name}/{self.name}"


def units_of(config: SweepConfig, cell: Cell) -> list[Unit]:
    """The cell's units; the first is its pre-training, on which the others depend."""
    units = [Unit(cell, "pretrain")]
    if spec.zeroshot_tasks(config, cell):
        units += [Unit(cell, "zeroshot", snapshot=frames) for frames in sorted(config.zeroshot_snapshots)]
        units.append(Unit(cell, "zeroshot"))
    units += [Unit(cell, "finetune", task) for task in spec.finetune_tasks(config, cell)]
    return units


def group_of(config: SweepConfig, cell: Cell) -> list[Cell]:
    """The cells whose pre-training runs with ``cell``'s in one group (itself alone when
    ``seeds_per_job`` is 1); the first is the group's leader."""
    if config.seeds_per_job == 1:
        return [cell]
    return next(group for group in spec.job_groups(config) if cell in group)


def jobs_of(config: SweepConfig, only: list[spec.Cell] | None = None) -> list[tuple[Unit, list[Unit]]]:
    """What the executors run: each pre-training job (a cell's, or a group leader's for the group)
    with the units that wait for it (its cell's other phases; a group's run as groups too, in
    the leader's units). With ``only``, the jobs of those cells (a group's when one of its cells
    is among them)."""
    jobs = []
    for group in spec.job_groups(config) if config.seeds_per_job > 1 else [[c] for c in spec.cells(config)]:
        if only is not None and not any(cell in only for cell in group):
            continue
        units = units_of(config, group[0])
        jobs.append((units[0], units[1:]))
    return jobs


def grouped(config: SweepConfig, unit: Unit) -> list[Cell]:
    """The cells a unit runs for: its group's, for a group leader's unit (docs/members.md); else
    its own cell."""
    group = group_of(config, unit.cell)
    return group if group[0] == unit.cell else [unit.cell]


def find_unit(config: SweepConfig, cell_name: str, unit_name: str) -> Unit:
    for cell in spec.cells(config):
        if cell.name == cell_name:
            for unit in units_of(config, cell):
                if unit.name == unit_name:
                    return unit
    raise DvfbError(f"the sweep has no unit {cell_name}/{unit_name}")


# ---------------------------------------------------------------------------------------------
# progress on disk


def pretrain_target(config: SweepConfig, cell: Cell) -> int:
    return spec.cell_config(config, cell).frames


def cell_run(sweep: SweepDir, config: SweepConfig, cell: Cell) -> PretrainRun:
    """The cell's pre-training run directory, with the config the sweep gives it (it may not exist yet)."""
    return PretrainRun(sweep.run_path(cell), spec.cell_config(config, cell))


def pretrain_done(sweep: SweepDir, config: SweepConfig, cell: Cell) -> bool:
    return cell_run(sweep, config, cell).is_finished()


def missing_zeroshot_tasks(sweep: SweepDir, config: SweepConfig, cell: Cell, snapshot: int | None = None) -> list[str]:
    """The zero-shot tasks of the cell without a result for the snapshot (default: the final one)."""
    run = cell_run(sweep, config, cell)
    frames = run.config.frames if snapshot is None else snapshot
    return [t for t in spec.zeroshot_tasks(config, cell)
            if not run.zeroshot_result(t, frames).is_file() or run.damaged_zeroshot_result(t, frames) is not None]


def set_aside_damaged_results(sweep: SweepDir, config: SweepConfig, unit: Unit) -> list[str]:
    """Before a zero-shot unit runs: each damaged result of its cells (a file cut short, moved or
    edited, :meth:`~dvfb.runs.layout.PretrainRun.damaged_zeroshot_result`) renamed to
    ``<file>.damaged`` beside it, so that the unit computes it again and nothing is lost; returns
    one line per file."""
    lines = []
    for member in grouped(config, unit):
        run = cell_run(sweep, config, member)
        frames = run.config.frames if unit.snapshot is None else unit.snapshot
        for task in spec.zeroshot_tasks(config, member):
            why = run.damaged_zeroshot_result(task, frames)
            if why is not None:
                path = run.zeroshot_result(task, frames)
                path.replace(path.with_name(path.name + ".damaged"))
                lines.append(f"[sweep] {why}: not counted; set aside as {path.name}.damaged and evaluated again")
    return lines


def finetune_run(sweep: SweepDir, config: SweepConfig, cell: Cell, task: str) -> FinetuneRun:
    """The cell's fine-tuning run of ``task`` (its directory; it may not exist yet)."""
    return FinetuneRun(cell_run(sweep, config, cell).finetune_path(task), None)


def is_done(sweep: SweepDir, config: SweepConfig, unit: Unit) -> bool:
    """Whether the unit has nothing left to do; a group leader's unit: for every member."""
    cells = grouped(config, unit)
    if unit.phase == "pretrain":
        return all(pretrain_done(sweep, config, cell) for cell in cells)
    if unit.phase == "zeroshot":
        return not any(missing_zeroshot_tasks(sweep, config, cell, unit.snapshot) for cell in cells)
    return all(finetune_run(sweep, config, cell, unit.task).is_finished() for cell in cells)


def _continue_flags(run_dir: Path) -> list[str]:
    """--resume from the latest checkpoint; --overwrite for a run stopped before its first one
    (its directory holds nothing that a restart would lose). A directory with results (snapshots,
    zero-shot results, fine-tuning runs) but neither a checkpoint nor a summary is never
    overwritten: that is a person's edit to look at, not a run to redo."""
    if latest_checkpoint(run_dir) is not None:
        return ["--resume"]
    if not run_dir.exists():
        return []
    kept = [name for name in ("snapshots", "zeroshot", "finetune") if any((run_dir / name).glob("*"))]
    if kept:
        raise UnitFailed(f"{run_dir} holds results ({', '.join(kept)}) but no checkpoint and no finished summary, so "
                         "the sweep would have to start it over; move the directory away to do that, or restore "
                         "its pretrain_summary.json")
    return ["--overwrite"]


def recover_summaries(sweep: SweepDir, config: SweepConfig, unit: Unit) -> list[str]:
    """Before a pre-training unit runs: each of its cells that finished but lost its
    pretrain_summary.json gets it rebuilt (:meth:`~dvfb.runs.layout.PretrainRun.recovered_summary`)
    instead of being trained again; returns one line per cell."""
    lines = []
    for member in grouped(config, unit):
        run = cell_run(sweep, config, member)
        if run.summary_path.exists() or not run.path.is_dir():
            continue
        summary = run.recovered_summary()
        if summary is not None:
            run.write_summary(summary)
            lines.append(f"[sweep] {run.path} had finished at {summary.frames} frames but had lost its "
                         f"{run.summary_path.name}; rebuilt it from its records (without wall-clock figures)")
    return lines


def command(sweep: SweepDir, config: SweepConfig, unit: Unit, torch_threads: int) -> list[str]:
    """The ``dvfb`` arguments that run (or continue) the unit; the unit must not be done."""
    cell = unit.cell
    run = sweep.run_path(cell)
    group = grouped(config, unit)
    if len(group) > 1 and unit.phase == "pretrain":
        # One process for the group's seeds (docs/members.md); it resumes when its members have
        # checkpoints (written together), and starts over when none has one yet.
        runs = [sweep.run_path(c) for c in group]
        resume = any(latest_checkpoint(r) is not None for r in runs)
        again = [] if resume or not any(r.exists() for r in runs) else ["--overwrite"]
        # The group's CPUs as single-thread shares, one per CPU up to one per member, as dvfb
        # pretrain --seeds does by default (docs/sweeps.md, "Threads"); never more threads than CPUs.
        processes = min(len(group), max(1, torch_threads))
        return ["pretrain", "--agent", cell.agent, "--domain", cell.domain,
                "--seeds", ",".join(str(c.seed) for c in group), "--preset", config.preset,
                "--run-dir", str(sweep.runs_dir / spec.group_run_template(cell)), "--no-progress",
                "--torch-threads", str(torch_threads), "--processes", str(processes), *spec.pretrain_flags(cell),
                *(["--resume"] if resume else again)]
    if unit.phase == "pretrain":
        return ["pretrain", "--agent", cell.agent, "--domain", cell.domain, "--seed", str(cell.seed),
                "--preset", config.preset, "--run-dir", str(run), "--no-progress",
                "--torch-threads", str(torch_threads), *spec.pretrain_flags(cell), *_continue_flags(run)]
    for member in group:
        if not pretrain_done(sweep, config, member):
            raise UnitFailed(f"{unit.key}: the pre-training of {member.name} has not finished")
        _check_snapshot(cell_run(sweep, config, member), unit)
    runs = [str(sweep.run_path(member)) for member in group]
    if unit.phase == "zeroshot":
        # A group evaluates together the members that lack a task's result (docs/members.md).
        missing = [t for t in spec.zeroshot_tasks(config, cell)
                   if any(t in missing_zeroshot_tasks(sweep, config, member, unit.snapshot) for member in group)]
        snapshot = ["--snapshot", str(unit.snapshot)] if unit.snapshot is not None else []
        return ["zeroshot", *runs, "--task", *missing, *snapshot, *(["--skip-existing"] if len(group) > 1 else [])]
    flags = [_continue_flags(finetune_run(sweep, config, member, unit.task).path) for member in group]
    # A group's members checkpoint together: one resumes, one starts over, the whole group does.
    flag = ["--resume"] if ["--resume"] in flags else (["--overwrite"] if ["--overwrite"] in flags else [])
    return ["finetune", *runs, "--task", unit.task, "--no-progress", *flag]


def _check_snapshot(run: PretrainRun, unit: Unit) -> None:
    """A unit that evaluates or fine-tunes a snapshot needs its file. A finished pre-training can
    lack it when its directory came from a commit of the small result files only (the sweep's
    ``.gitignore``): then the unit fails with the reason rather than training the cell again."""
    frames = unit.snapshot if unit.snapshot is not None else run.config.frames
    if not run.snapshot_path(frames).is_file():
        raise UnitFailed(f"{unit.key}: {run.path} has finished pre-training but not its snapshot after {frames} "
                         "frames (results copied without snapshots?); to pre-train the cell again, move its "
                         "directory away and repeat the sweep command")


def read_state(sweep: SweepDir, unit: Unit) -> dict | None:
    path = sweep.state_path(unit)
    return read_json(path) if path.is_file() else None


def _write_state(sweep: SweepDir, unit: Unit, **fields: Any) -> dict:
    state = read_state(sweep, unit) or {"unit": unit.key, "attempts": 0}
    state.update(fields)
    write_json_atomic(sweep.state_path(unit), state)
    return state


def slurm_job_id() -> str | None:
    """This process's SLURM job as squeue names it (``123_4`` for an array task), if any."""
    env = os.environ
    if env.get("SLURM_ARRAY_JOB_ID") and env.get("SLURM_ARRAY_TASK_ID"):
        return f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}"
    return env.get("SLURM_JOB_ID")


# ---------------------------------------------------------------------------------------------
# running a unit


# A request to stop: set by a signal handler (the local sweep's SIGINT/SIGTERM, a SLURM job's USR2)
# and read by the loops that wait for phases, which then stop their phase with SIGTERM and wait
# for its checkpoint outside any handler. Setting an Event never blocks.
_stop = threading.Event()


def request_stop() -> None:
    """Ask every running phase of this process to checkpoint and stop, and no new one to start.
    Safe in a signal handler: it only sets a flag."""
    _stop.set()


def stop_requested() -> bool:
    return _stop.is_set()


def clear_stop() -> None:
    _stop.clear()


def _die_with_parent_and_ignore_usr2() -> None:
    # The phase ignores USR2: SLURM sends it to every process of the job step before a time limit,
    # and the runner, not the phase, decides what to do (SIGTERM, so that the phase checkpoints).
    signal.signal(signal.SIGUSR2, signal.SIG_IGN)
    # Linux: the phase gets SIGTERM when the worker thread that started it dies, so that a killed
    # submitter leaves no phase running that a re-run would start a second time.
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _wait_for_phase(child: subprocess.Popen, stop: Callable[[], bool], grace_s: float = STOP_GRACE_S) -> int:
    """Wait for the phase; when ``stop()`` becomes true, send it SIGTERM once (it checkpoints and
    exits as interrupted) and kill it if it has not exited after ``grace_s``."""
    stopped_at = None
    while True:
        try:
            return child.wait(timeout=0.25)
        except subprocess.TimeoutExpired:
            pass
        if stopped_at is None and stop():
            child.send_signal(signal.SIGTERM)
            stopped_at = time.monotonic()
        elif stopped_at is not None and time.monotonic() - stopped_at > grace_s:
            child.kill()


def _interrupted(returncode: int) -> bool:
    return any(returncode in (-int(s), 128 + int(s)) for s in _INTERRUPT_SIGNALS)


def _exit_reason(log: Path, offset: int, returncode: int) -> str:
    """The last non-empty line the attempt wrote to its log, and how the process ended."""
    try:
        with open(log, "rb") as file:
            file.seek(offset)
            lines = [line.strip() for line in file.read().decode("utf-8", "replace").splitlines() if line.strip()]
    except OSError:
        lines = []
    ending = (f"killed by {signal.Signals(-returncode).name}" if returncode < 0 else f"exit status {returncode}")
    return f"{ending}: {lines[-1]}" if lines else ending


# The command line's entry point, for the debug executor. The CLI hands it down when it starts a
# sweep (sweeps never import the CLI, which stands above them).
_in_process_main = None


def use_in_process(main) -> None:
    """Run the debug executor's phases with ``main(argv) -> exit code`` (the ``dvfb`` command)."""
    global _in_process_main
    _in_process_main = main


def _run_in_process(argv: list[str], log: Path) -> int:
    """``dvfb ARGV`` in this process (debug executor), its error output copied to the log."""
    main = _in_process_main
    if main is None:
        raise DvfbError("the debug executor runs dvfb commands in this process: start the sweep with the dvfb "
                        "command (dvfb sweep run ... --executor debug)")
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors):
            code = main(argv)
    except SystemExit as exc:  # argparse's exit (a flag it refuses): the unit's failure, said and recorded
        code = exc.code if isinstance(exc.code, int) else 1
    except Exception:  # noqa: BLE001 - recorded as the unit's failure, like a crashed subprocess
        errors.write(traceback.format_exc())
        code = 1
    with open(log, "a", encoding="utf-8") as file:
        file.write(errors.getvalue())
    sys.stderr.write(errors.getvalue())
    return code


def _run_subprocess(argv: list[str], log: Path, torch_threads: int, stop: Callable[[], bool]) -> int:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if torch_threads > 0:
        # numpy and the BLAS under it get the same share of the cores as torch.
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[name] = str(torch_threads)
    with open(log, "ab") as out:
        child = subprocess.Popen([sys.executable, "-m", "dvfb", *argv], stdout=out, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, env=env, preexec_fn=_die_with_parent_and_ignore_usr2)
        return _wait_for_phase(child, stop)


def run_unit(sweep_path: str, cell_name: str, unit_name: str, torch_threads: int, in_process: bool = False,
             stop: Callable[[], bool] | None = None) -> str:
    """Run (or continue) one unit of the sweep in ``sweep_path``; ``"done"`` or ``"skipped"``
    (it was done already). Raises UnitFailed or UnitInterrupted with the reason and log path.

    This is what every executor calls, in a worker thread, a SLURM job or this process. The phase
    is stopped (SIGTERM, then it checkpoints) when :func:`request_stop` was called or ``stop()``
    becomes true; a unit asked to stop before it starts does not start.
    """
    def stopping() -> bool:
        return stop_requested() or (stop is not None and stop())

    sweep = SweepDir(sweep_path)
    config = spec.load_stored(sweep.path)
    unit = find_unit(config, cell_name, unit_name)
    for line in recover_summaries(sweep, config, unit) if unit.phase == "pretrain" else ():
        print(line, file=sys.stderr, flush=True)
    if is_done(sweep, config, unit):
        if (read_state(sweep, unit) or {}).get("state") != "done":
            _write_state(sweep, unit, state="done")
        return "skipped"
    if stopping():
        raise UnitInterrupted(f"{unit.key} was not started: the sweep is stopping")
    log = sweep.log_path(unit)
    log.parent.mkdir(parents=True, exist_ok=True)
    damaged = set_aside_damaged_results(sweep, config, unit) if unit.phase == "zeroshot" else []
    for line in damaged:
        print(line, file=sys.stderr, flush=True)
    try:
        argv = command(sweep, config, unit, torch_threads)
    except UnitFailed as exc:
        _write_state(sweep, unit, state="failed", ended=time.time(), reason=str(exc))
        raise
    attempts = (read_state(sweep, unit) or {}).get("attempts", 0) + 1
    with open(log, "a", encoding="utf-8") as file:
        file.write(f"\n=== attempt {attempts} on {socket.gethostname()} at {time.strftime('%Y-%m-%d %H:%M:%S')}: "
                   f"dvfb {' '.join(argv)}\n" + "".join(f"{line}\n" for line in damaged))
    offset = log.stat().st_size
    _write_state(sweep, unit, state="running", attempts=attempts, started=time.time(), ended=None,
                 exit_code=None, reason=None, log=str(log), host=socket.gethostname(), pid=os.getpid(),
                 job_id=slurm_job_id(), command=["dvfb", *argv])
    code = _run_in_process(argv, log) if in_process else _run_subprocess(argv, log, torch_threads, stopping)
    reason = _exit_reason(log, offset, code)
    if code == 0 and is_done(sweep, config, unit):
        _write_state(sweep, unit, state="done", ended=time.time(), exit_code=0)
        return "done"
    if code == 0:
        code, reason = 1, f"exit status 0 but the results are missing: {reason}"
    if _interrupted(code):
        _write_state(sweep, unit, state="interrupted", ended=time.time(), exit_code=code, reason=reason)
        raise UnitInterrupted(f"{unit.key} was interrupted ({reason}); log: {log}")
    _write_state(sweep, unit, state="failed", ended=time.time(), exit_code=code, reason=reason)
    raise UnitFailed(f"{unit.key} failed ({reason}); log: {log}")


def mark_failed(sweep: SweepDir, unit: Unit, reason: str) -> None:
    """Close a unit whose process is gone without having recorded its end."""
    _write_state(sweep, unit, state="failed", ended=time.time(), reason=reason)


def mark_requeued(sweep_path: str, cell_name: str, unit_name: str, why: str = "time limit or preemption") -> None:
    """Record that the unit's job stopped its phase to be requeued (SLURM time-out/preemption)."""
    sweep = SweepDir(sweep_path)
    unit = find_unit(spec.load_stored(sweep.path), cell_name, unit_name)
    _write_state(sweep, unit, state="interrupted", ended=time.time(), reason=f"requeued by SLURM ({why})")
