"""A text progress bar on stderr, for long commands (video export, loading a
big case)."""
from __future__ import annotations

import math
import sys
import time

__all__ = ["format_clock", "ProgressBar"]


def format_clock(t_s: float) -> str:
    """``m:ss.s`` (or ``h:mm:ss`` from an hour on) for a duration [s]."""
    t = max(0.0, float(t_s))
    if t >= 3600:
        h, r = divmod(int(round(t)), 3600)
        return f"{h}:{r // 60:02d}:{r % 60:02d}"
    m, s = divmod(t, 60.0)
    if round(s, 1) >= 60.0:
        m, s = m + 1, 0.0
    return f"{int(m)}:{s:04.1f}"


class ProgressBar:
    """A one-line text progress bar with percent and ETA (on stderr).

    On a terminal the line is redrawn in place at most every ``min_interval_s``;
    elsewhere (a log file) a line is printed every 10 %.

    Parameters
    ----------
    total : int
        Work units (e.g. frames).
    label : str
        Shown before the bar.
    stream : file, optional
        Default ``sys.stderr``.
    width : int
        Bar width [characters].
    clock : callable
        Wall-clock source [s] (tests pass a fake).
    """

    def __init__(self, total: int, label: str = "", stream=None, width: int = 30,
                 min_interval_s: float = 0.2, clock=time.monotonic):
        self.total = max(int(total), 1)
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.width = int(width)
        self.min_interval_s = float(min_interval_s)
        self.clock = clock
        self.t_start = clock()
        self.done = 0
        self._last_draw = -math.inf
        self._last_decile = -1
        self._final_drawn = False
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty and isatty())

    def text(self, done: int | None = None, now: float | None = None) -> str:
        """The bar for ``done`` units at time ``now``."""
        done = self.done if done is None else int(done)
        now = self.clock() if now is None else now
        frac = min(max(done / self.total, 0.0), 1.0)
        fill = int(frac * self.width)
        bar = "#" * fill + "." * (self.width - fill)
        elapsed = now - self.t_start
        if done >= self.total:
            tail = f"done in {format_clock(elapsed)}"
        elif done > 0:
            tail = f"ETA {format_clock(elapsed * (self.total - done) / done)}"
        else:
            tail = "ETA ?"
        lead = f"{self.label} " if self.label else ""
        return f"{lead}[{bar}] {100 * frac:3.0f}%  {done}/{self.total}  {tail}"

    def update(self, done: int) -> None:
        """Record progress and redraw if due."""
        self.done = int(done)
        now = self.clock()
        if self.tty:
            if now - self._last_draw >= self.min_interval_s or self.done >= self.total:
                self.stream.write("\r" + self.text(now=now))
                self.stream.flush()
                self._last_draw = now
                self._final_drawn = self.done >= self.total
        else:
            dec = int(10 * min(self.done / self.total, 1.0))
            if dec > self._last_decile:
                self.stream.write(self.text(now=now) + "\n")
                self.stream.flush()
                self._last_decile = dec

    def close(self) -> None:
        """Draw the final state and end the line."""
        if self.tty:
            # the finished bar is drawn once: a transcript of the terminal shows
            # no second "done" line
            self.stream.write("\n" if self._final_drawn else "\r" + self.text() + "\n")
            self.stream.flush()
        elif int(10 * min(self.done / self.total, 1.0)) > self._last_decile:
            self.update(self.done)
