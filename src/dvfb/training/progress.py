"""Progress of a loop (a progress bar, or periodic lines off a terminal) and status lines."""

from __future__ import annotations

import os
import sys
import time

from tqdm import tqdm


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


def progress_bars(enabled: bool | None, unit: str = "transition"):
    """``(total, what) -> Progress``: how the data layer's readers and writers report progress
    (``enabled`` as :class:`Progress` takes it; False: nothing)."""
    if enabled is False:
        return None
    return lambda total, what: Progress(total, 0, what, enabled, unit=unit)
