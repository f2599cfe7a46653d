"""Pieces shared by the pretrain / zeroshot / finetune workflows.

* seeding and device set-up;
* :class:`MetricWindow` -- keeps per-update metric tensors on the device and reads them back in one
  host sync every ``log_every`` steps, checking for NaN/inf losses at the same time;
* loading a pre-trained agent from a run directory with the checks that keep users from mixing
  runs (wrong agent, wrong config, missing or corrupt files);
* the progress bar.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from dvfb import envs
from dvfb.agents import Agent, make_agent
from dvfb.config import to_dict
from dvfb.errors import CheckpointError, ConfigError, NonFiniteLossError, RunDirError, RunInterrupted
from dvfb.runs import RunDir, list_snapshots, load_snapshot
from dvfb.workflows.config import PretrainConfig, agent_sections, load_run_config, resolve_device, run_config_from_dict

SNAPSHOT_PREFIX = "snapshot_"
# Format of agent snapshots. 1: written before the agent registry (DVFB/FB only, no "format"
# key); 2: adds the format, the domain, and the agent's full run config for every method.
SNAPSHOT_FORMAT = 2


def seed_everything(seed: int) -> np.random.Generator:
    """Seed torch and Python; return the numpy Generator the workflow draws uniform actions from."""
    torch.manual_seed(seed)
    random.seed(seed)
    return np.random.default_rng(seed)


def setup_torch(config: PretrainConfig) -> torch.device:
    if config.torch_threads > 0:
        torch.set_num_threads(config.torch_threads)
    return resolve_device(config.device)


def rng_state(generator: np.random.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "python": random.getstate(),
            "numpy": generator.bit_generator.state,
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def restore_rng_state(state: dict, generator: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    random.setstate(state["python"])
    generator.bit_generator.state = state["numpy"]
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    ``flush`` stacks the window into one tensor, copies it to the host (the only sync), raises
    :class:`NonFiniteLossError` naming the first update and loss that went NaN/inf, and returns
    the window means. (So a non-finite value is reported at the next flush, at most ``log_every``
    steps later, naming the exact step; no checkpoint is written in between, because every
    checkpoint flushes first.)
    """

    def __init__(self) -> None:
        self.steps: list[int] = []
        self.rows: list[dict[str, torch.Tensor]] = []

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        self.steps.append(step)
        self.rows.append(metrics)

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
        keys = list(self.rows[0])
        table = torch.stack([torch.stack([row[k].float().reshape(()) for k in keys]) for row in self.rows])
        values = table.cpu().numpy()
        steps, self.steps, self.rows = self.steps, [], []
        bad = ~np.isfinite(values)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            bad_keys = [keys[c] for c in np.flatnonzero(bad[row])]
            hint = ""
            if any("implicit_reward" in k for k in bad_keys):
                hint = ("; the implicit reward B Cov(B)^-1 z is not finite: Cov(B) is singular or "
                        "ill-conditioned, add a ridge with --fb.cov-ridge 1e-6 (or larger)")
            raise NonFiniteLossError(f"non-finite value {keys[col]}={values[row, col]} at step {steps[row]} "
                                     f"(non-finite there: {', '.join(bad_keys)}){hint}")
        return dict(zip(keys, values.mean(0).tolist()))


def check_action(action: np.ndarray, step: int, window: MetricWindow) -> None:
    """Stop on a non-finite action (a diverged actor) before MuJoCo rejects it.

    Flushing the window first names the first non-finite loss when one is there.
    """
    if not np.isfinite(action).all():
        window.flush()
        raise NonFiniteLossError(f"the policy produced a non-finite action at step {step}")


def checkpoint_note(last_checkpoint: int | None) -> str:
    """What a user can resume from after a failure: the truth about the checkpoints."""
    if last_checkpoint is None:
        return "no resume checkpoint had been written yet"
    return f"the resume checkpoint of step {last_checkpoint} is intact (--resume continues from it)"


@contextlib.contextmanager
def reported_failures(what: str, run_path: Path, last_checkpoint: Callable[[], int | None]):
    """Around a training loop: a non-finite loss or a disk error (full, read-only, permissions)
    becomes one line that says what stopped and which checkpoint is intact."""
    try:
        yield
    except NonFiniteLossError as exc:
        raise NonFiniteLossError(f"{exc}; {what} stopped, {checkpoint_note(last_checkpoint())}") from exc
    except OSError as exc:
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        raise RunDirError(f"cannot write to {run_path}: {exc.strerror or exc}{where}; {what} stopped, "
                          f"{checkpoint_note(last_checkpoint())}") from exc


def interrupted(stop: StopSignals, what: str, step: int, total: int, run_path: Path) -> RunInterrupted:
    """The error a loop raises after checkpointing on a signal."""
    return RunInterrupted(f"{stop.name} received: {what} stopped at step {step} of {total} with a checkpoint; "
                          f"continue with the same command plus --resume (run {run_path})", stop.received)


class StopSignals:
    """SIGTERM and SIGINT ask the loop to stop: it finishes its current step, writes a checkpoint and
    raises :class:`~dvfb.errors.RunInterrupted`. A second SIGINT stops at once (KeyboardInterrupt).

    Handlers are installed only in the main thread (signals cannot be caught elsewhere) and the
    previous ones are restored on exit.
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum, _frame) -> None:
        if self.received is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.received = signum

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for signum in self.SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    @property
    def name(self) -> str:
        return signal.Signals(self.received).name if self.received is not None else ""


class ResumeCheckpoints:
    """When a training loop writes its resume checkpoints, the same for pre-training and fine-tuning.

    * At an episode end, once ``every`` steps have passed since the last checkpoint, and at the
      last step (:meth:`episode_end`).
    * On SIGTERM / SIGINT (:class:`StopSignals`): after the current step, a checkpoint (mid-episode
      if need be) unless one was just written, then :class:`~dvfb.errors.RunInterrupted`
      (:meth:`after_step`).

    Every checkpoint flushes the metric window first, so a non-finite loss is never checkpointed.
    ``save(mid_episode)`` writes one; ``last`` is the step of the newest (None: none yet), which
    failures report (:func:`reported_failures`). Use as ``with checkpoints: <loop>``.
    """

    def __init__(self, save: Callable[[bool], None], window: MetricWindow, every: int, total: int, what: str,
                 run_path: Path, last: int | None = None):
        self.save, self.window, self.every, self.total = save, window, every, total
        self.what, self.run_path, self.last = what, run_path, last
        self.stop = StopSignals()
        self._guard = contextlib.ExitStack()

    def __enter__(self) -> ResumeCheckpoints:
        self._guard.enter_context(self.stop)
        self._guard.enter_context(reported_failures(self.what, self.run_path, lambda: self.last))
        return self

    def __exit__(self, *exc_info):
        return self._guard.__exit__(*exc_info)

    def _write(self, step: int, mid_episode: bool) -> None:
        self.window.flush()
        self.save(mid_episode)
        self.last = step

    def episode_end(self, step: int) -> None:
        if step - (self.last or 0) >= self.every or step >= self.total:
            self._write(step, mid_episode=False)

    def after_step(self, step: int, mid_episode: bool) -> None:
        if self.stop.received is None or step >= self.total:
            return
        if self.last != step:
            self._write(step, mid_episode)
        else:
            self.window.flush()
        raise interrupted(self.stop, self.what, step, self.total, self.run_path)


def notify(message: str) -> None:
    """A one-line status message of a run on stderr (memory estimate, resume point, progress)."""
    print(message, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Memory


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


# ---------------------------------------------------------------------------------------------
# Progress


class Progress:
    """Progress of a loop in frames (or steps): a tqdm bar on a terminal; without one (cluster logs,
    CI) a line every ``DVFB_PROGRESS_SECONDS`` seconds (default 30) with frames, frames/s and ETA.

    ``enabled``: True always shows the bar, False shows nothing, None decides by the terminal.
    """

    def __init__(self, total: int, initial: int, desc: str, enabled: bool | None = None, unit: str = "frame"):
        self.total, self.done, self.desc, self.unit = total, initial, desc, unit
        terminal = sys.stderr.isatty()
        self.bar = None
        self.interval = None
        if enabled or (enabled is None and terminal):
            self.bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, unit_scale=True,
                            dynamic_ncols=True, smoothing=0.05)
        elif enabled is None:
            self.interval = float(os.environ.get("DVFB_PROGRESS_SECONDS", "30"))
        self._start_time = self._last_line = time.monotonic()
        self._start_done = initial

    def update(self, n: int = 1) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        elif self.interval is not None:
            now = time.monotonic()
            if now - self._last_line >= self.interval:
                self._last_line = now
                self.line(now)

    def line(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        rate = (self.done - self._start_done) / max(now - self._start_time, 1e-9)
        remaining = (self.total - self.done) / rate if rate > 0 else float("inf")
        eta = time.strftime("%H:%M:%S", time.gmtime(remaining)) if remaining < 86400 * 365 else "?"
        notify(f"[{self.desc}] {self.done}/{self.total} {self.unit}s ({100 * self.done / max(self.total, 1):.0f}%), "
               f"{rate:.1f} {self.unit}s/s, ETA {eta}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# ---------------------------------------------------------------------------------------------
# Snapshots of pre-trained agents


def snapshot_name(frames: int) -> str:
    return f"{SNAPSHOT_PREFIX}{frames}"


def snapshot_state(agent: Agent, config: PretrainConfig, frames: int) -> dict:
    """A self-describing snapshot: the agent's name, its run config, the dims, the format version
    and the state of its pre-trained modules."""
    return {"kind": "pretrained_agent", "format": SNAPSHOT_FORMAT, "agent": agent.name, "domain": config.domain,
            "config": to_dict(config), "frames": frames, "obs_dim": agent.obs_dim, "action_dim": agent.action_dim,
            "modules": {k: m.state_dict() for k, m in agent.pretrained_modules().items()}}


def available_snapshots(run: RunDir) -> list[int]:
    """Frames of the run's agent snapshots, ascending."""
    names = list_snapshots(run)
    return sorted(int(n[len(SNAPSHOT_PREFIX):]) for n in names
                  if n.startswith(SNAPSHOT_PREFIX) and n[len(SNAPSHOT_PREFIX):].isdigit())


def open_pretrained_run(run_path: str | Path) -> tuple[RunDir, PretrainConfig]:
    """Open a pre-training run and apply its ``torch_threads`` (acting is batch-1 forward passes,
    which slow down badly when OpenMP threads compete for busy cores)."""
    run = RunDir.open(run_path)
    try:
        config = load_run_config(run.config_path)
    except ConfigError as exc:
        if str(run.config_path) in str(exc):
            raise
        raise ConfigError(f"{run.config_path}: {exc}") from exc
    if config.torch_threads > 0:
        torch.set_num_threads(config.torch_threads)
    return run, config


def check_snapshot(state: dict, config: PretrainConfig, where: str) -> None:
    """Refuse a snapshot of another method, domain, configuration or format, naming both sides."""
    if state.get("kind") != "pretrained_agent":
        raise CheckpointError(f"{where} is not a dvfb agent snapshot")
    fmt = state.get("format", 1)
    if not isinstance(fmt, int) or fmt > SNAPSHOT_FORMAT:
        raise CheckpointError(f"{where} has snapshot format {fmt!r}, newer than this dvfb reads "
                              f"({SNAPSHOT_FORMAT}); upgrade dvfb")
    if state.get("agent") != config.agent:
        raise CheckpointError(f"{where} was written by agent {state.get('agent')!r} but the run is configured for "
                              f"agent {config.agent!r}")
    stored = state.get("config")
    if not isinstance(stored, dict):
        raise CheckpointError(f"{where} has no run config")
    domain = state.get("domain", stored.get("domain"))
    if domain != config.domain:
        raise CheckpointError(f"{where} was trained on domain {domain!r} but the run is configured for domain "
                              f"{config.domain!r}")
    try:
        # Through the same strict reader, so that fields added since the snapshot take their defaults.
        stored_sections = agent_sections(run_config_from_dict(stored, where))
    except ConfigError as exc:
        raise CheckpointError(f"{where}: {exc}") from exc
    wanted = agent_sections(config)
    diffs = [f"{section}.{key}: snapshot {stored_sections[section].get(key)!r}, run {value!r}"
             for section, values in wanted.items() for key, value in values.items()
             if stored_sections[section].get(key) != value]
    if diffs:
        raise CheckpointError(f"{where} was written with another configuration than the run's config.json ("
                              + "; ".join(diffs[:4]) + (" ..." if len(diffs) > 4 else "") + ")")


def load_pretrained_agent(run: RunDir, config: PretrainConfig, snapshot: int | None = None,
                          device: str | torch.device | None = None) -> tuple[Agent, int]:
    """Rebuild the run's agent from a snapshot (the newest by default), through the registry.

    Raises :class:`CheckpointError` if the run has no snapshot, the snapshot is unreadable, or it
    was written by another method, for another domain or shape, or with another configuration
    than the run's ``config.json``.
    """
    frames = available_snapshots(run)
    if not frames:
        raise CheckpointError(f"run {run.path} has no pre-trained snapshot in {run.snapshots_dir}; "
                              "has pre-training finished?")
    if snapshot is None:
        snapshot = frames[-1]
    elif snapshot not in frames:
        raise CheckpointError(f"run {run.path} has no snapshot at {snapshot} frames; available: {frames}")
    state = load_snapshot(run, snapshot_name(snapshot), map_location="cpu")
    where = f"snapshot {run.snapshots_dir / snapshot_name(snapshot)}.pt"
    check_snapshot(state, config, where)
    device = device if device is not None else resolve_device(config.device)
    return agent_from_snapshot(state, config, device, where), snapshot


def agent_from_snapshot(state: dict, config: PretrainConfig, device: str | torch.device, where: str) -> Agent:
    """Build the snapshot's agent (registry) and load its pre-trained modules; a module of another
    shape is an error that names both shapes."""
    agent = make_agent(config.agent, state["obs_dim"], state["action_dim"], config, device)
    try:
        for key, module in agent.pretrained_modules().items():
            module.load_state_dict(state["modules"][key])
    except (KeyError, RuntimeError) as exc:
        raise CheckpointError(f"{where} does not fit the configured networks: {exc}") from exc
    return agent


def check_task_in_domain(task: str, domain: str) -> None:
    """A zero-shot/fine-tuning task must share the pre-training domain's dynamics (docs/tasks.md §5)."""
    if task not in envs.TASKS:
        envs.make(task)  # raises ConfigError listing the valid names
    task_domain = envs.TASKS[task].domain
    if task_domain != domain:
        raise ConfigError(f"task {task!r} belongs to domain {task_domain!r}, but the run was pre-trained "
                          f"on {domain!r}; valid tasks: {', '.join(envs.tasks_of_domain(domain))}")
