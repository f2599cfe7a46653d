"""Progress of a loop (a progress bar, or periodic lines off a terminal) and status lines."""

from __future__ import annotations

import collections
import os
import sys
import time

from tqdm import tqdm

from dvfb.core.errors import ConfigError


def notify(message: str) -> None:
    """A one-line status message of a run on stderr (memory estimate, resume point, progress)."""
    print(message, file=sys.stderr, flush=True)


# The ETA's rate is that of the last minute, not the average since the start: a run whose machine
# becomes busy (another job, a second command) slows down many times over, and an average would
# promise an end long past (README.md, "Threads and progress").
WINDOW_SECONDS = 60.0
PROGRESS_ENV = "DVFB_PROGRESS_SECONDS"


def progress_interval() -> float:
    """The seconds between progress lines off a terminal: ``DVFB_PROGRESS_SECONDS`` (default 30; 0:
    a line at every step). A value that is not a number >= 0 is a :class:`~dvfb.core.errors.ConfigError`."""
    text = os.environ.get(PROGRESS_ENV, "30")
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value < float("inf"):
        raise ConfigError(f"{PROGRESS_ENV}={text!r} is not a number of seconds >= 0 (the interval between progress "
                          "lines when stderr is not a terminal; default 30)")
    return value


def format_eta(seconds: float) -> str:
    """``HH:MM:SS``, with the days in front past one (``2d 03:04:05``); ``?`` when unknown."""
    if not seconds < 86400 * 365:
        return "?"
    days, rest = divmod(int(seconds), 86400)
    clock = time.strftime("%H:%M:%S", time.gmtime(rest))
    return f"{days}d {clock}" if days else clock


class Progress:
    """Progress of a loop in frames (or steps): a tqdm bar on a terminal; without one (cluster logs,
    CI) a line every ``DVFB_PROGRESS_SECONDS`` seconds (default 30) with frames, frames/s and ETA,
    the rate and ETA of the last :data:`WINDOW_SECONDS` (the average since the start before then).

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
            self.interval = progress_interval()
        self._last_line = time.monotonic()
        # (time, done) about once a second: the oldest one kept is the first of the window.
        self._samples: collections.deque[tuple[float, int]] = collections.deque([(self._last_line, initial)])

    def update(self, n: int = 1, now: float | None = None) -> None:
        """``n`` more done, at ``now`` (``time.monotonic()``'s clock; default: its reading)."""
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        elif self.interval is not None:
            now = time.monotonic() if now is None else now
            self._sample(now)
            if now - self._last_line >= self.interval:
                self._last_line = now
                self.line(now)

    def _sample(self, now: float) -> None:
        samples = self._samples
        if now - samples[-1][0] >= WINDOW_SECONDS / 60:
            samples.append((now, self.done))
        while len(samples) > 2 and samples[1][0] <= now - WINDOW_SECONDS:
            samples.popleft()

    def rate(self, now: float | None = None) -> float:
        """Units per second over the last :data:`WINDOW_SECONDS` (since the start before then)."""
        now = time.monotonic() if now is None else now
        since, done = self._samples[0]
        return (self.done - done) / max(now - since, 1e-9)

    def line(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        rate = self.rate(now)
        remaining = (self.total - self.done) / rate if rate > 0 else float("inf")
        notify(f"[{self.desc}] {self.done}/{self.total} {self.unit}s ({100 * self.done / max(self.total, 1):.0f}%), "
               f"{rate:.1f} {self.unit}s/s, ETA {format_eta(remaining)}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def progress_bars(enabled: bool | None, unit: str = "transition"):
    """``(total, what) -> Progress``: how the data layer's readers and writers report progress
    (``enabled`` as :class:`Progress` takes it; False: nothing)."""
    if enabled is False:
        return None
    return lambda total, what: Progress(total, 0, what, enabled, unit=unit)
