"""What a workflow checks before it starts: the device and threads, the memory a run needs, that a
task belongs to the run's domain, and what a command evaluates (a run directory, or the one an
exported model is evaluated in)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.core.errors import ConfigError
from dvfb.nets.execution import resolve_device
from dvfb.runs.export import evaluation_run, is_export, remove_evaluation_run
from dvfb.runs.directory import RunDir
from dvfb.runs.layout import PretrainRun
from dvfb.runs.machine import cores, default_torch_threads
from dvfb.runs.run_config import PretrainConfig
from dvfb.training.progress import notify


def use_threads(requested: int | None = 0, run_setting: int = 0) -> int:
    """Set this process's torch threads (README.md, "Threads and progress") and return them:
    ``requested`` (a command's ``--torch-threads``) when positive; when None (not given to a command
    on a run), the run's own ``torch_threads`` if it set one; otherwise :func:`default_torch_threads`.
    Never more than the CPUs this process may use (a run made on a large node, evaluated on a
    laptop; ``--torch-threads 10000``; ``OMP_NUM_THREADS=1000``): more runnable OpenMP threads than
    cores make every operator wait for descheduled threads, and a run crawls. An explicit request
    above the CPUs says so in one line."""
    if requested:
        threads, asked = requested, f"--torch-threads {requested}"
    elif requested is None and run_setting > 0:
        threads, asked = run_setting, None  # the run's own setting, quietly fitted to this machine
    else:
        threads = default_torch_threads()
        asked = f"OMP_NUM_THREADS={threads}" if os.environ.get("OMP_NUM_THREADS", "").strip() else None
    threads = fit_threads(threads, asked)
    torch.set_num_threads(threads)
    return threads


_SAID: set[str] = set()  # the lines fit_threads has printed in this process (once each)


def fit_threads(threads: int, asked: str | None = None) -> int:
    """``threads``, at most :func:`~dvfb.runs.machine.cores`; when ``asked`` (what asked for them,
    e.g. ``--torch-threads 10000``) names a request above the CPUs, one line says what is used."""
    limit = cores()
    if threads <= limit:
        return threads
    line = (f"[threads] {asked} is more than the {limit} CPU(s) this process may use; using {limit} "
            "(more threads than CPUs make OpenMP crawl)")
    if asked is not None and line not in _SAID:
        _SAID.add(line)
        notify(line)
    return limit


def resume_threads(run: RunDir, requested: int | None) -> int:
    """Set the threads of a resume and return them (README.md, "Threads and progress"): a resume
    computes with the threads the run computed with (:meth:`~dvfb.runs.directory.RunDir.computed_threads`), so that it ends
    bit-identical to an uninterrupted run, whatever ``OMP_NUM_THREADS`` the resuming shell has.
    ``requested`` (a positive ``--torch-threads``) wins, and one line says that the numbers may
    then differ; so does a machine with fewer CPUs than the run used."""
    recorded = run.computed_threads()
    if requested:
        threads = fit_threads(requested, f"--torch-threads {requested}")
        if recorded and threads != recorded:
            notify(f"[threads] resuming {run.path} with {threads} torch thread(s) instead of the {recorded} it ran "
                   "with (--torch-threads): its numbers may differ from an uninterrupted run's")
    elif recorded:
        threads = fit_threads(recorded)
        if threads != recorded:
            notify(f"[threads] {run.path} ran with {recorded} torch threads, but this process may use "
                   f"{threads} CPU(s); resuming with {threads}: its numbers may differ from an uninterrupted run's")
    else:
        threads = fit_threads(default_torch_threads())
    torch.set_num_threads(threads)
    return threads


def setup_torch(config: PretrainConfig) -> torch.device:
    use_threads(config.torch_threads)
    return resolve_device(config.device)


def open_run(path, torch_threads: int | None = None) -> PretrainRun:
    """Open a pre-training run and set the threads of the command that uses it (:func:`use_threads`:
    ``torch_threads``, else the run's own setting, else the default); acting is batch-1 forward
    passes, which slow down badly when OpenMP threads compete for busy cores."""
    run = PretrainRun.open(path)
    use_threads(torch_threads, run.config.torch_threads)
    return run


@contextlib.contextmanager
def run_or_export(path, eval_dir=None, command: list[str] | None = None
                  ) -> Iterator[tuple[Path, dict[str, np.ndarray] | None]]:
    """What a command evaluates, as ``(run directory, inference data)``: a run directory as it is
    (no data), or for an exported model (docs/sharing.md, "Evaluate") the run directory it is
    evaluated in (``eval_dir``, by default ``<DIR>.eval`` beside it; made the first time) with the
    export's inference samples. A directory made here is removed again when the command fails
    before anything was written in it; the export's own files are only read."""
    if not is_export(path):
        if eval_dir is not None:
            raise ConfigError(f"--eval-dir is where an exported model is evaluated; {path} is not an exported model")
        yield Path(path), None
        return
    run, export, created = evaluation_run(path, eval_dir, command)
    notify(f"[export] {path} is an exported model; evaluating it in {run.path}" + (" (made now)" if created else ""))
    try:
        yield run.path, export.inference_data
    except BaseException:
        if created:
            remove_evaluation_run(run)
        raise


def available_memory_bytes() -> int | None:
    """MemAvailable of /proc/meminfo (Linux), None elsewhere."""
    try:
        with open("/proc/meminfo", encoding="ascii") as file:
            for line in file:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} PiB"


def learner_state_bytes(agent: torch.nn.Module) -> int:
    """About what the networks hold during training: parameters, gradients and Adam's two moments."""
    return sum(p.numel() * p.element_size() * (4 if p.requires_grad else 1) for p in agent.parameters())


def check_memory(parts: dict[str, int], what: str, device: torch.device) -> None:
    """Print the memory estimate of a run and refuse one that cannot fit the machine (host memory;
    on CUDA the replay and networks live on the GPU, whose free memory is checked instead)."""
    total = sum(parts.values())
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        available, where = free, f"free on {device}"
    else:
        available, where = available_memory_bytes(), "available"
    detail = " + ".join(f"{name} {format_bytes(n)}" for name, n in parts.items())
    notify(f"[{what}] memory estimate: {detail} = {format_bytes(total)}"
           + (f" ({format_bytes(available)} {where})" if available is not None else ""))
    if available is not None and total > available:
        raise ConfigError(f"{what} needs about {format_bytes(total)} ({detail}) but only {format_bytes(available)} "
                          f"is {where}; lower --replay-capacity or the network sizes")


def check_task_in_domain(task: str, domain: str) -> None:
    """A zero-shot/fine-tuning task must share the pre-training domain's dynamics (docs/tasks.md §5)."""
    if task not in envs.TASKS:
        envs.make(task)  # raises ConfigError listing the valid names
    task_domain = envs.TASKS[task].domain
    if task_domain != domain:
        raise ConfigError(f"task {task!r} belongs to domain {task_domain!r}, but the run was pre-trained "
                          f"on {domain!r}; valid tasks: {', '.join(envs.tasks_of_domain(domain))}")


def evaluation_tasks(config, requested: list[str]) -> list[str]:
    """The tasks a run is evaluated on: ``requested`` (``["all"]``: every task of its domain),
    each checked. A run that learned one task's reward (the supervised reference) is evaluated on
    that task only: its policy on another task would be read as a reference it is not."""

    trained = get_spec(config.agent).task_of(config)
    if requested == ["all"]:
        return [trained] if trained is not None else list(envs.tasks_of_domain(config.domain))
    for task in requested:
        check_task_in_domain(task, config.domain)
        if trained is not None and task != trained:
            raise ConfigError(f"this {config.agent} run learned {trained!r}; it is evaluated on that task only, "
                              f"not {task!r}")
    return list(requested)


def check_replay(capacity: int, capacity_flag: str, needs, episode_length: int, domain: str) -> None:
    """Before anything is created: the replay must hold a whole episode, and the batches the learner
    asks for (n-step successors, s_{t+2}) must exist within one episode."""
    if capacity < episode_length:
        raise ConfigError(f"{capacity_flag} {capacity} must be at least the episode length of {domain} "
                          f"({episode_length}), so that the episode in progress fits")
    horizon = max(needs.nstep, 2 if needs.need_future else 1)
    if horizon >= episode_length:
        raise ConfigError(f"the learner's batches need successors {horizon} steps ahead (n-step n = {needs.nstep}), "
                          f"but {domain} episodes have {episode_length} steps; lower the n-step setting")

