"""Stopping on a signal: SIGTERM and SIGINT ask a loop to checkpoint and stop (docs/methods.md,
"Training loop")."""

from __future__ import annotations

import signal
import threading
from collections.abc import Sequence
from pathlib import Path

from dvfb.core.errors import RunInterrupted


class StopSignals:
    """SIGTERM and SIGINT ask the loop to stop: it finishes its current step, writes a checkpoint and
    raises :class:`~dvfb.core.errors.RunInterrupted`. A second SIGINT stops at once (KeyboardInterrupt).

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


def run_directories(run_paths: Path | Sequence[Path]) -> str:
    """``run DIR``, or for a group's members ``runs DIR, DIR, ...``: where a message says the loop wrote."""
    paths = [run_paths] if isinstance(run_paths, (str, Path)) else list(run_paths)
    return f"run {paths[0]}" if len(paths) == 1 else "runs " + ", ".join(str(p) for p in paths)


def interrupted(stop: StopSignals, what: str, step: int, total: int,
                run_paths: Path | Sequence[Path]) -> RunInterrupted:
    """The error a loop raises after checkpointing on a signal; it names every run directory the
    loop wrote (a group's members: each one, not the folder they share)."""
    return RunInterrupted(f"{stop.name} received: {what} stopped at step {step} of {total} with a checkpoint; "
                          f"continue with the same command plus --resume ({run_directories(run_paths)})",
                          stop.received)
