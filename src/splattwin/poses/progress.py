"""Progress of long pose-estimation steps, live in a terminal and readable in a redirected log.

On a TTY: a rich progress bar (stage, count, elapsed). Otherwise (stderr redirected to a file or a CI
log): plain lines, one when a stage starts, at most one every `interval` seconds while it runs, and its
last count when it ends (the next stage starts or the work is done) unless that was already the last line,
so a log shows that SfM is alive and how far each step got, without carriage-return noise.
(`splattwin.progress.Progress` is the same rule for one counted task; this class has named stages.)
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class StageProgress:
    """`update(description, done, total)` as often as you like; `tick()` re-prints a heartbeat line when
    output is plain and `interval` seconds passed. Use as a context manager."""

    def __init__(self, enabled: bool = True, stream: TextIO | None = None, interval: float = 5.0,
                 prefix: str = "SfM"):
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval
        self.prefix = prefix
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._rich = None
        self._task = None
        self._state: tuple[str, int, int] | None = None
        self._printed: tuple[str, int, int] | None = None   # the state of the last plain line
        self._stage_t0 = time.monotonic()
        self._last_print = 0.0

    def __enter__(self) -> "StageProgress":
        if self.enabled and self.tty:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._rich = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                  TimeElapsedColumn(), console=Console(file=self.stream), transient=False)
            self._rich.__enter__()
            self._task = self._rich.add_task(self.prefix, total=1)
        return self

    def __exit__(self, *exc) -> bool:
        if self._rich is not None:
            self._rich.__exit__(*exc)
            self._rich = None
        else:
            self._finish()
        return False

    def _finish(self) -> None:
        """Plain output: the current stage's last count, unless it is what the last line said."""
        if self.enabled and self._rich is None and self._state is not None and self._state != self._printed:
            self._print()

    def update(self, description: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        new_stage = self._state is None or self._state[0] != description
        if new_stage:
            self._finish()
            self._stage_t0 = time.monotonic()
        total = max(int(total), 1)
        done = min(int(done), total)   # a count past its total (an estimate too low) is shown as done, never 639/600
        self._state = (description, done, total)
        if self._rich is not None:
            self._rich.update(self._task, description=description, completed=done, total=total)
        elif new_stage or time.monotonic() - self._last_print >= self.interval:
            self._print()

    def tick(self) -> None:
        """Heartbeat for plain output: repeat the current line every `interval` seconds."""
        if self.enabled and self._rich is None and self._state is not None \
                and time.monotonic() - self._last_print >= self.interval:
            self._print()

    def message(self, text: str) -> None:
        """A one-off line (a retry starting, a stage result)."""
        if not self.enabled:
            return
        if self._rich is not None:
            self._rich.console.print(text, markup=False, highlight=False)
        else:
            # the current stage's last count first: it was printed after the retry's first lines, with a
            # count that contradicted the message ("retrying ... 2/8 registered", then "mapping: 3/8")
            self._finish()
            self.stream.write(f"{text}\n")
            self.stream.flush()

    def _print(self) -> None:
        desc, done, total = self._state  # type: ignore[misc]
        el = time.monotonic() - self._stage_t0
        self.stream.write(f"{desc}: {done}/{total} ({el:.0f} s)\n")
        self.stream.flush()
        self._last_print = time.monotonic()
        self._printed = self._state
