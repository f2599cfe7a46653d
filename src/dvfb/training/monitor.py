"""What watches a training loop: metrics, progress, signals, checkpoints at the right moments.

* :class:`MetricWindow` -- keeps per-update metric tensors on the device and reads them back in one
  host sync every ``log_every`` steps, checking for NaN/inf values at the same time;
* :func:`check_action` -- stops on a non-finite action before the physics rejects it;
* :class:`StopSignals`, :class:`ResumeCheckpoints`, :func:`reported_failures` -- SIGTERM/SIGINT,
  checkpoints at episode ends and on signals, one-line failures naming the intact checkpoint;
* :class:`Progress` and :func:`notify` -- a progress bar (or periodic lines) and status messages.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from dvfb.errors import NonFiniteLossError, RunDirError, RunInterrupted


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    ``flush`` stacks the window into one tensor, copies it to the host (the only sync), raises
    :class:`NonFiniteLossError` naming the first update and loss that went NaN/inf, and returns
    the window means. (So a non-finite value is reported at the next flush, at most ``log_every``
    steps later, naming the exact step; no checkpoint is written in between, because every
    checkpoint flushes first.)
    """

    def __init__(self, hint: Callable[[list[str]], str] | None = None) -> None:
        self.steps: list[int] = []
        self.rows: list[dict[str, torch.Tensor]] = []
        # What the method can tell about its non-finite metrics (Agent.nonfinite_hint).
        self.hint = hint

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        self.steps.append(step)
        self.rows.append(metrics)

    def _read(self, shape: tuple) -> tuple[list[str], np.ndarray, list[int]]:
        """The window as ``(keys, values (updates, metrics, *shape), steps)`` in one host sync, emptied."""
        keys = list(self.rows[0])
        table = torch.stack([torch.stack([row[k].float().reshape(shape) for k in keys]) for row in self.rows])
        steps, self.steps, self.rows = self.steps, [], []
        return keys, table.cpu().numpy(), steps

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
        keys, values, steps = self._read(())
        message = nonfinite_message(keys, values, steps, self.hint)
        if message is not None:
            raise NonFiniteLossError(message)
        return dict(zip(keys, values.mean(0).tolist()))


def nonfinite_message(keys: list[str], values: np.ndarray, steps: list[int], hint) -> str | None:
    """The one line naming the first update and loss of a ``(updates, metrics)`` table that went
    NaN/inf (with the method's hint), or None when every value is finite."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    row, col = np.argwhere(bad)[0]
    bad_keys = [keys[c] for c in np.flatnonzero(bad[row])]
    hint = hint(bad_keys) if hint is not None else ""
    hint = f"; {hint}" if hint else ""
    return (f"non-finite value {keys[col]}={values[row, col]} at step {steps[row]} "
            f"(non-finite there: {', '.join(bad_keys)}){hint}")


class GroupWindow(MetricWindow):
    """A group's metric window (docs/members.md): per-update metrics of shape ``(M,)``, one entry
    per live member, read back in one host sync per window for all members.

    A member whose metrics went non-finite is reported to ``on_fault(member, message)`` (which
    stops it) and the others go on; :meth:`member_window` gives each member a window of its own
    to read its means from. ``members()`` lists the live members in stack order.
    """

    def __init__(self, members: Callable[[], list], on_fault: Callable[[object, str], None],
                 hint: Callable[[list[str]], str] | None = None) -> None:
        super().__init__(hint)
        self.members, self.on_fault = members, on_fault
        self.pending: dict[int, dict[str, float]] = {}

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
        keys, values, steps = self._read((-1,))  # values: (updates, metrics, members)
        faults = []
        for i, member in enumerate(self.members()):
            message = nonfinite_message(keys, values[:, :, i], steps, self.hint)
            if message is None:
                self.pending[id(member)] = dict(zip(keys, values[:, :, i].mean(0).tolist()))
            else:
                faults.append((member, message))
        for member, message in faults:
            self.on_fault(member, message)
        return {}

    def member_window(self, member) -> MemberWindow:
        return MemberWindow(self, member)


class MemberWindow:
    """One member's view of a :class:`GroupWindow`: :meth:`flush` gives its own window means."""

    def __init__(self, group: GroupWindow, member) -> None:
        self.group, self.member = group, member

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        raise RuntimeError("a group's metrics go to its GroupWindow")

    def flush(self) -> dict[str, float]:
        self.group.flush()
        return self.group.pending.pop(id(self.member), {})


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

    def ensure(self, step: int, mid_episode: bool) -> None:
        """A checkpoint of ``step`` unless the newest is of it (a run that must end with one)."""
        if self.last != step:
            self._write(step, mid_episode)

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
