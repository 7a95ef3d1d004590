"""`calib demo`'s console: the story's text on stdout, the progress bar on stderr."""
from __future__ import annotations

import re
import sys
import textwrap
import time


WIDTH = 100
"""Columns of the story's text."""


class DemoError(Exception):
    """What stops the demo, said in one line."""


# ----------------------------------------------------------------------------------------------- output

def say(text: str = "", indent: int = 0) -> None:
    pad = " " * indent
    print(textwrap.fill(text, WIDTH, initial_indent=pad, subsequent_indent=pad + "  ", break_on_hyphens=False,
                        break_long_words=False) if text else "", flush=True)


def head(text: str) -> None:
    print(f"\n{text}", flush=True)


def fmm(v: float) -> str:
    return f"{v:.3f} mm"


def table(rows: list[tuple[str, dict]]) -> None:
    """Aligned `label   0.123 mm RMS, max 0.456 mm` lines."""
    w = max(len(label) for label, _ in rows) + 2
    for label, e in rows:
        print(f"   {label + ':':<{w}} {e['rms_mm']:8.3f} mm RMS, max {e['max_mm']:8.3f} mm", flush=True)


def _stem(message: str | None) -> str:
    """A job message without the elapsed time the worker appends ('testing 33 causes (12.0 s)')."""
    return re.sub(r" \(\d+(\.\d+)? s\)$", "", message or "")


class ProgressBar:
    """A text bar on stderr: redrawn in place on a terminal, one line per new message otherwise (and one every
    LOG_EVERY_S while a step lasts, so a log shows the demo alive).

    The fraction shown never goes back (a job's later stage can report less than an earlier one: the Motoman's bar
    went 78 % -> 36 %), and the time shown is the wall time since the bar started, queue included, from the demo's
    own clock (the worker's message carries the job's run time, which stood still while the job was queued)."""

    LOG_EVERY_S = 30.0

    def __init__(self, stream=sys.stderr, width: int = 30, clock=time.monotonic):
        self.stream, self.width, self.clock = stream, width, clock
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.last = None
        self.shown = 0.0  # the largest fraction shown so far
        self.t0 = clock()
        self.logged = self.t0

    def update(self, fraction: float, message: str | None) -> None:
        self.shown = max(self.shown, min(max(float(fraction or 0.0), 0.0), 1.0))
        n = int(round(self.shown * self.width))
        now = self.clock()
        stem = _stem(message)
        line = f"  [{'#' * n}{'.' * (self.width - n)}] {100 * self.shown:3.0f} %  {now - self.t0:5.1f} s  {stem}"
        if self.tty:
            self.stream.write("\r" + line[:WIDTH].ljust(WIDTH))
            self.stream.flush()
        elif stem != _stem(self.last) or now - self.logged >= self.LOG_EVERY_S:
            self.stream.write(line + "\n")  # a log gets a line per step (and per LOG_EVERY_S), not per poll
            self.stream.flush()
            self.logged = now
        self.last = message

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
