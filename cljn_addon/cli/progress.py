"""The one progress display of the command line: every command (denoise, normals, train, eval,
demo, bench) passes a `Progress` as the engine's progress(fraction, message) callback."""
from __future__ import annotations

import os
import sys
import time


class Progress:
    """progress(fraction, message) callback: a tqdm bar with ETA on a terminal, plain lines
    (every 10 %, with an estimate of the time left) otherwise; with `every` seconds also a
    line at least that often (long runs: training). Use it as a context manager or close()."""

    def __init__(self, label: str, enabled: bool = True, stream=None, every: float | None = None):
        self.label = label
        self.every = every
        self.last_line = time.monotonic()
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.bar = None
        self.start = time.monotonic()
        self.last_step = -1
        self.last_message = None
        self.done = 0.0

    def __call__(self, fraction, message=""):
        if not self.enabled:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        if self.tty:
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=100.0, desc=self.label, file=self.stream, leave=False,
                                **_terminal_size(self.stream),
                                bar_format="{desc}: {percentage:3.0f}%|{bar}| "
                                           "[{elapsed}<{remaining}]{postfix}")
            value = round(100.0 * fraction, 2)
            if message != self.last_message:
                self.bar.set_postfix_str(message, refresh=False)
                self.last_message = message
            if value > self.done:
                self.bar.update(value - self.done)
                self.done = value
            else:
                self.bar.refresh()
            return
        step = int(fraction * 10)
        due = self.every is not None and time.monotonic() - self.last_line >= self.every
        if step > self.last_step or due:
            self.last_step = max(step, self.last_step)
            self.last_line = time.monotonic()
            elapsed = time.monotonic() - self.start
            eta = ""
            if 0.0 < fraction < 1.0 and elapsed > 1.0:
                eta = f", about {_duration(elapsed * (1.0 - fraction) / fraction)} left"
            text = f"{self.label}: {100.0 * fraction:3.0f}%{eta}" + (f" ({message})" if message
                                                                     else "")
            print(text, file=self.stream, flush=True)

    def close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _terminal_size(stream) -> dict:
    """tqdm size overrides for terminals that report a size of 0 (tqdm then draws nothing)."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, OSError, ValueError):
        return {}
    out = {}
    if size.columns <= 0:
        out["ncols"] = 80
    if size.lines <= 0:
        out["nrows"] = 24
    return out


def _duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    if seconds < 90:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 90:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"
