"""Where the units of a sweep run (README "Sweeps", docs/sweeps.md).

* ``debug``: in this process, one unit after the other (each cell's pre-training first).
* ``local``: a pool of worker threads, at most the number of cores, each running one unit as a
  ``dvfb`` subprocess with ``cores / workers`` torch threads; a cell's zero-shot and fine-tuning
  units start when its pre-training has finished, before any pre-training that has not started,
  so that cells finish (and their results can be kept) one after the other. (submitit's local executor starts every
  job at once and knows no dependencies, hence this pool.)
* ``slurm``: submitit job arrays, one per phase, with a concurrency limit and per-phase
  resources. A zero-shot or fine-tuning array has the same cells at the same indices as the
  pre-training array and depends on it with ``aftercorr``: task i starts when pre-training task i
  has succeeded, and is cancelled if it failed (``--kill-on-invalid-dep=yes``). The job ids are
  recorded in ``SWEEP/jobs.json``; a re-run waits for the jobs of an earlier submission that are
  still queued or running (squeue) instead of submitting them again. Without SLURM accounting
  there is no ``sacct``: the submitter learns a job's fate from squeue and the unit's state file,
  never from sacct.

A job that SLURM times out or preempts gets USR2 (submitit), stops its phase (SIGTERM, so that the
phase checkpoints where it can), and requeues itself; an ``scontrol requeue`` kills and restarts
the job. Either way the restarted job runs the unit again, which resumes from the run's checkpoint.
"""

from __future__ import annotations

import concurrent.futures
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dvfb.core.errors import DvfbError, RunInterrupted
from dvfb.runs import read_json, write_json_atomic
from dvfb.runs.machine import cores
from dvfb.sweep import spec
from dvfb.sweep.spec import SweepConfig
from dvfb.sweep.units import (
    SweepDir,
    Unit,
    UnitFailed,
    UnitInterrupted,
    clear_stop,
    find_unit,
    is_done,
    jobs_of,
    mark_failed,
    mark_requeued,
    read_state,
    request_stop,
    run_unit,
    units_of,
)


def _import_submitit():
    # Importing submitit configures logging (logging.config.dictConfig), which closes the handlers
    # already installed, an application's or pytest's. NOCONFIG leaves them alone; the variable is
    # restored at once, so that the jobs, which inherit the environment at sbatch time, still log.
    previous = os.environ.get("SUBMITIT_LOG_LEVEL")
    os.environ["SUBMITIT_LOG_LEVEL"] = "NOCONFIG"
    try:
        # inside the NOCONFIG set above (its import configures logging)
        import submitit
        import submitit.helpers
    finally:
        if previous is None:
            del os.environ["SUBMITIT_LOG_LEVEL"]
        else:
            os.environ["SUBMITIT_LOG_LEVEL"] = previous
    return submitit


submitit = _import_submitit()


class SlurmError(DvfbError):
    """The SLURM commands are missing or fail (no cluster, controller down)."""


@dataclass
class Outcome:
    """What became of the units of one run of a sweep."""

    done: list[str] = field(default_factory=list)  # unit keys finished by this run
    skipped: list[str] = field(default_factory=list)  # finished before
    failed: dict[str, str] = field(default_factory=dict)  # unit key -> reason (with the log path)


def _say(message: str) -> None:
    print(f"[sweep] {message}", flush=True)


def _record(outcome: Outcome, unit: Unit, run: Callable[[], str], interrupt_stops: bool = False) -> bool:
    """Run a unit and file its outcome; True when it finished. With ``interrupt_stops`` an
    interrupted unit (Ctrl-C in the debug executor's own process) stops the sweep."""
    try:
        result = run()
    except UnitInterrupted as exc:
        if interrupt_stops:
            raise RunInterrupted(f"{exc}; repeat the command to continue", signal.SIGINT) from None
        outcome.failed[unit.key] = str(exc)
        _say(f"FAILED {exc}")
        return False
    except UnitFailed as exc:
        outcome.failed[unit.key] = str(exc)
        _say(f"FAILED {exc}")
        return False
    except Exception as exc:  # noqa: BLE001 - one broken cell (a corrupt run directory) must not stop the others
        outcome.failed[unit.key] = f"{unit.key} could not run: {type(exc).__name__}: {exc}"
        _say(f"FAILED {outcome.failed[unit.key]}")
        return False
    (outcome.done if result == "done" else outcome.skipped).append(unit.key)
    _say(f"{result} {unit.key}")
    return True


def _dependents_not_run(outcome: Outcome, units: list[Unit], why: str) -> None:
    for unit in units:
        outcome.failed[unit.key] = f"{unit.key} not run: {why}"


# ---------------------------------------------------------------------------------------------
# debug and local


def run_debug(sweep: SweepDir, config: SweepConfig, only: list[spec.Cell] | None = None) -> Outcome:
    outcome = Outcome()
    threads = config.torch_threads
    for first, rest in jobs_of(config, only):
        if _record(outcome, first, lambda u=first: run_unit(str(sweep.path), u.cell.name, u.name, threads, True), True):
            for unit in rest:
                _record(outcome, unit, lambda u=unit: run_unit(str(sweep.path), u.cell.name, u.name, threads, True), True)
        else:
            _dependents_not_run(outcome, rest, f"the pre-training of {first.cell.name} did not finish")
    return outcome


def run_local(sweep: SweepDir, config: SweepConfig, only: list[spec.Cell] | None = None) -> Outcome:
    """The worker pool. SIGINT (Ctrl-C) or SIGTERM stops the sweep: no further unit starts, the
    running phases get SIGTERM and checkpoint, and the sweep raises RunInterrupted once they have
    exited (exit status 128 + the signal); repeating the command continues it."""
    workers = min(config.workers or cores(), cores())
    threads = config.torch_threads or max(1, cores() // workers)
    _say(f"local executor: {workers} worker(s), {threads} torch thread(s) each")
    outcome = Outcome()
    pending: dict[concurrent.futures.Future, tuple[Unit, list[Unit]]] = {}
    # Units wait here, not in the pool's queue, so that a finished pre-training's dependents go
    # ahead of the pre-trainings that have not started (a cell is done as early as it can be).
    waiting: list[tuple[Unit, list[Unit]]] = list(jobs_of(config, only))
    received: list[int] = []

    def on_signal(signum, frame) -> None:
        received.append(signum)
        request_stop()  # only sets a flag; the waiting workers stop their phases

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    clear_stop()
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dvfb-sweep") as pool:
            def fill() -> None:
                while waiting and len(pending) < workers and not received:
                    unit, dependents = waiting.pop(0)
                    future = pool.submit(run_unit, str(sweep.path), unit.cell.name, unit.name, threads)
                    pending[future] = (unit, dependents)

            fill()
            while pending:
                finished, _ = concurrent.futures.wait(pending, timeout=0.5,
                                                      return_when=concurrent.futures.FIRST_COMPLETED)
                for future in finished:
                    unit, dependents = pending.pop(future)
                    if _record(outcome, unit, future.result) and not received:
                        waiting[:0] = [(dependent, []) for dependent in dependents]
                    elif not received:
                        _dependents_not_run(outcome, dependents, f"the pre-training of {unit.cell.name} did not finish")
                fill()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        clear_stop()
    if received:
        name = signal.Signals(received[0]).name
        raise RunInterrupted(f"stopped by {name}: {len(outcome.done)} unit(s) finished, the running ones checkpointed; "
                             f"repeat the command to continue (dvfb sweep status {sweep.path})", received[0])
    return outcome


# ---------------------------------------------------------------------------------------------
# slurm


def _slurm(*args: str) -> str:
    try:
        result = subprocess.run(list(args), capture_output=True, text=True, timeout=60)
    except FileNotFoundError:
        raise SlurmError(f"{args[0]} is not installed: the slurm executor needs a SLURM cluster "
                         "(scripts/slurm_cluster.sh start for a local one), or use --executor local") from None
    except subprocess.TimeoutExpired:
        raise SlurmError(f"{' '.join(args)} did not answer within 60 s") from None
    if result.returncode != 0:
        raise SlurmError(f"{' '.join(args)} failed: {(result.stderr or result.stdout).strip()}")
    return result.stdout


def alive_jobs() -> dict[str, str]:
    """Queued or running jobs, one entry per array task: ``{"123_4": "RUNNING", ...}``."""
    jobs = {}
    for line in _slurm("squeue", "-h", "-r", "-o", "%i %T").splitlines():
        parts = line.split()
        if len(parts) == 2:
            jobs[parts[0]] = parts[1]
    return jobs


def _sbatch_options(lines: list[str]) -> dict:
    """``--key=value`` / ``--key value`` / ``--flag`` texts as submitit's additional parameters."""
    options: dict = {}
    tokens = [t for line in lines for t in shlex.split(line)]
    i = 0
    while i < len(tokens):
        token = tokens[i]
        if not token.startswith("--"):
            raise DvfbError(f"slurm.extra_sbatch: expected --option[=value], got {token!r}")
        if "=" in token:
            key, value = token[2:].split("=", 1)
        elif i + 1 < len(tokens) and not tokens[i + 1].startswith("--"):
            key, value = token[2:], tokens[i + 1]
            i += 1
        else:
            key, value = token[2:], True
        options[key] = value
        i += 1
    return options


class UnitJob(submitit.helpers.Checkpointable):
    """A unit in a SLURM job.

    Before a time limit (and on preemption) SLURM sends USR2 to every process of the job. The phase
    ignores it (docs/sweeps.md); here a handler only records it, and the loop that waits for the
    phase, outside the handler, stops the phase with SIGTERM (it checkpoints and exits as
    interrupted). Then submitit's own USR2 handler is called from ordinary code: it calls
    :meth:`checkpoint` (which records the requeue) and requeues the job, whose next attempt
    resumes the unit from its checkpoint. Nothing blocking runs inside a signal handler.
    """

    def __call__(self, sweep_path: str, cell_name: str, unit_name: str, torch_threads: int) -> str:
        received: list[int] = []
        submitit_handler = signal.getsignal(signal.SIGUSR2)
        signal.signal(signal.SIGUSR2, lambda signum, frame: received.append(signum))
        try:
            return run_unit(sweep_path, cell_name, unit_name, torch_threads, stop=lambda: bool(received))
        except UnitInterrupted:
            if received and callable(submitit_handler):
                submitit_handler(received[0], None)  # checkpoint(), requeue, exit
            raise
        finally:
            signal.signal(signal.SIGUSR2, submitit_handler)

    def checkpoint(self, sweep_path: str, cell_name: str, unit_name: str, torch_threads: int):
        # Only a file write: submitit calls this from its signal handler when USR2 comes before
        # the unit started (the phase, if any, has already stopped when it is called from above).
        mark_requeued(sweep_path, cell_name, unit_name)
        return super().checkpoint(sweep_path, cell_name, unit_name, torch_threads)


def _slurm_executor(sweep: SweepDir, config: SweepConfig):
    s = config.slurm
    executor = submitit.SlurmExecutor(folder=sweep.slurm_dir / "%j", max_num_timeout=s.max_requeues,
                                      python=s.python or sys.executable)
    common = dict(array_parallelism=s.array_parallelism, signal_delay_s=s.signal_delay_s, setup=list(s.setup),
                  stderr_to_stdout=True)
    for name in ("partition", "account", "qos"):
        if getattr(s, name) is not None:
            common[name] = getattr(s, name)
    executor.update_parameters(**common)
    return executor


def _submit_array(executor, config: SweepConfig, phase: str, units: list[Unit], dependency: str | None,
                  sweep: SweepDir) -> list[str]:
    """Submit the units as one array with the phase's resources; their job ids, in order."""
    resources: spec.Resources = getattr(config.slurm, phase)
    threads = config.torch_threads or resources.cpus
    extra = _sbatch_options(config.slurm.extra_sbatch)
    if dependency is not None:
        extra.update({"dependency": dependency, "kill-on-invalid-dep": "yes"})
    params = dict(job_name=f"dvfb-{phase}", cpus_per_task=resources.cpus, mem=f"{resources.mem_gb:g}GB",
                  time=resources.time_min, additional_parameters=extra)
    if resources.gpus:
        params["gpus_per_node"] = resources.gpus
    executor.update_parameters(**params)
    try:
        with executor.batch():
            jobs = [executor.submit(UnitJob(), str(sweep.path), u.cell.name, u.name, threads) for u in units]
    except Exception as exc:  # submitit raises plain exceptions when sbatch fails
        if isinstance(exc, DvfbError):
            raise
        raise SlurmError(f"submitting the {phase} jobs failed: {exc}") from exc
    return [job.job_id for job in jobs]


def run_slurm(sweep: SweepDir, config: SweepConfig, only: list[spec.Cell] | None = None) -> Outcome:
    alive = alive_jobs()
    recorded: dict[str, str] = read_json(sweep.jobs_path) if sweep.jobs_path.is_file() else {}
    # What was done before this run started: the summary counts each unit once, as done before,
    # done now or failed.
    jobs = jobs_of(config, only)
    done_before = [u.key for cell in (spec.cells(config) if only is None else only) for u in units_of(config, cell)
                   if is_done(sweep, config, u)]

    def in_flight(unit: Unit) -> str | None:
        job = recorded.get(unit.key)
        return job if job is not None and job in alive else None

    executor = _slurm_executor(sweep, config)
    submitted: dict[str, str] = {}
    pretrain_batch: list[Unit] = []  # cells whose pre-training is submitted now
    ready: dict[str, list[Unit]] = {}  # phase -> units whose pre-training is done: no dependency
    after_flight: list[tuple[Unit, str]] = []  # units whose pre-training job is still in flight
    dependents = {first.key: rest for first, rest in jobs}
    for first, rest in jobs:
        todo = [u for u in rest if not is_done(sweep, config, u) and in_flight(u) is None]
        if is_done(sweep, config, first):
            for unit in todo:
                ready.setdefault(unit.phase, []).append(unit)
        elif in_flight(first) is not None:
            after_flight += [(unit, in_flight(first)) for unit in todo]
        else:
            pretrain_batch.append(first)
    if pretrain_batch:
        ids = _submit_array(executor, config, "pretrain", pretrain_batch, None, sweep)
        submitted.update({u.key: j for u, j in zip(pretrain_batch, ids)})
        array_id = ids[0].split("_")[0]
        # Aligned arrays: task i of each depends on task i of the pre-training array.
        by_cell = {first.cell.name: dependents[first.key] for first in pretrain_batch}
        names = sorted({u.name for first in pretrain_batch for u in by_cell[first.cell.name]})
        for name in names:
            aligned = [next((u for u in by_cell[first.cell.name] if u.name == name), None) for first in pretrain_batch]
            if config.seeds_per_job > 1:  # a group's dependents are several cells' units: one job each
                for first in pretrain_batch:
                    after_flight += [(u, submitted[first.key]) for u in by_cell[first.cell.name] if u.name == name]
            elif all(u is not None for u in aligned):
                ids = _submit_array(executor, config, aligned[0].phase, aligned, f"aftercorr:{array_id}", sweep)
                submitted.update({u.key: j for u, j in zip(aligned, ids)})
            else:  # a unit not every cell has (fine-tuning a task of one domain): one job each
                for first, unit in zip(pretrain_batch, aligned):
                    if unit is not None:
                        after_flight.append((unit, submitted[first.key]))
    for phase, units in ready.items():
        ids = _submit_array(executor, config, phase, units, None, sweep)
        submitted.update({u.key: j for u, j in zip(units, ids)})
    for unit, job in after_flight:
        [job_id] = _submit_array(executor, config, unit.phase, [unit], f"afterok:{job}", sweep)
        submitted[unit.key] = job_id
    recorded.update(submitted)
    write_json_atomic(sweep.jobs_path, recorded)
    waiting = {key: job for key, job in recorded.items() if key in submitted or job in alive}
    _say(f"slurm: {len(submitted)} job(s) submitted, {len(waiting) - len(submitted)} still in flight from an "
         f"earlier submission; jobs in {sweep.slurm_dir}")
    return _wait_for_jobs(sweep, config, {k: j for k, j in waiting.items() if k not in done_before}, done_before)


def _wait_for_jobs(sweep: SweepDir, config: SweepConfig, waiting: dict[str, str],
                   done_before: list[str]) -> Outcome:
    units = {key: find_unit(config, *key.split("/")) for key in waiting}
    started = {key: (read_state(sweep, unit) or {}).get("attempts", 0) for key, unit in units.items()}
    reported: set[str] = set()
    while True:
        alive = alive_jobs()
        for key, unit in units.items():
            if key not in reported and waiting[key] not in alive:
                reported.add(key)
                state = read_state(sweep, unit) or {}
                _say(f"{state.get('state', 'ended')} {key} (job {waiting[key]})")
        if all(job not in alive for job in waiting.values()):
            break
        time.sleep(config.slurm.poll_s)
    outcome = Outcome(skipped=list(done_before))
    for key, unit in units.items():
        state = read_state(sweep, unit) or {}
        if is_done(sweep, config, unit):
            outcome.done.append(key)  # it was not done when this run started
        elif state.get("state") == "running":
            # The job is gone but the unit's state was never closed: the process was killed
            # (a signal, the time limit before the requeue handler ran, memory). Close it.
            reason = (f"killed: its job {waiting[key]} ended while the unit ran (a signal, out of time or out of "
                      f"memory); job log: {sweep.slurm_dir / waiting[key]}")
            mark_failed(sweep, unit, reason)
            outcome.failed[key] = f"{key} {reason}; log: {state.get('log')}"
        elif state.get("state") in ("failed", "interrupted") and state.get("attempts", 0) > started[key]:
            outcome.failed[key] = f"{key} {state['state']} ({state.get('reason')}); log: {state.get('log')}"
        else:
            outcome.failed[key] = (f"{key} not run: its job {waiting[key]} ended before running it (a dependency "
                                   f"failed, or the job was cancelled or timed out before it started); job log: "
                                   f"{sweep.slurm_dir}")
    return outcome


EXECUTORS: dict[str, Callable[[SweepDir, SweepConfig, list[spec.Cell] | None], Outcome]] = {
    "debug": run_debug, "local": run_local, "slurm": run_slurm}
