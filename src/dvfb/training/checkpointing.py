"""When a training loop writes its resume checkpoints (at episode ends, on signals, at the end),
and the one line a failure ends with (docs/methods.md, "Training loop")."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path
from typing import Callable

from dvfb.core.errors import NonFiniteLossError, RunDirError
from dvfb.training.metric_windows import MetricWindow
from dvfb.training.signals import StopSignals, interrupted, run_directories


def checkpoint_note(last_checkpoint: int | None) -> str:
    """What a user can resume from after a failure: the truth about the checkpoints."""
    if last_checkpoint is None:
        return "no resume checkpoint had been written yet"
    return f"the resume checkpoint of step {last_checkpoint} is intact (--resume continues from it)"


@contextlib.contextmanager
def reported_failures(what: str, run_path: Path | Sequence[Path], last_checkpoint: Callable[[], int | None]):
    """Around a training loop: a non-finite loss or a disk error (full, read-only, permissions)
    becomes one line that says what stopped and which checkpoint is intact (``run_path``: the run
    directory, or a group's member directories)."""
    try:
        yield
    except NonFiniteLossError as exc:
        raise NonFiniteLossError(f"{exc}; {what} stopped, {checkpoint_note(last_checkpoint())}") from exc
    except OSError as exc:
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        raise RunDirError(f"cannot write to {run_directories(run_path)}: {exc.strerror or exc}{where}; {what} "
                          f"stopped, {checkpoint_note(last_checkpoint())}") from exc


class ResumeCheckpoints:
    """When a training loop writes its resume checkpoints, the same for pre-training and fine-tuning.

    * At an episode end, once ``every`` steps have passed since the last checkpoint, and at the
      last step (:meth:`episode_end`).
    * On SIGTERM / SIGINT (:class:`StopSignals`): after the current step, a checkpoint (mid-episode
      if need be) unless one was just written, then :class:`~dvfb.core.errors.RunInterrupted`
      (:meth:`after_step`).

    Every checkpoint checks the metric window first (:meth:`MetricWindow.check`), so a non-finite
    loss is never checkpointed; the window's rows stay in it, and the checkpoint saves them.
    ``save(mid_episode)`` writes one; ``last`` is the step of the newest (None: none yet), which
    failures report (:func:`reported_failures`). Use as ``with checkpoints: <loop>``.
    """

    def __init__(self, save: Callable[[bool], None], window: MetricWindow, every: int, total: int, what: str,
                 run_path: Path | Sequence[Path], last: int | None = None):
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
        self.window.check()
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
            self.window.check()
        raise interrupted(self.stop, self.what, step, self.total, self.run_path)
