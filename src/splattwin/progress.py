"""Progress of long work: a bar with ETA in a terminal, plain timestamped lines in a redirected log.

Why our own front: the stages used tqdm and rich directly, and neither suits a log file, a CI job or a
cluster's stdout capture. tqdm there writes a carriage-return update every 0.1 s (a 3000-step training run
became ~1500 "lines" of bar redraws, 48 kB, with the stage's own messages lost among them); rich, when its
console is not a terminal, draws nothing until the task ends (a 10-minute stage looked hung). The same
rule as SfM's `poses.progress.StageProgress` now holds for every stage: on a TTY a rich bar (description,
bar, count, elapsed, ETA, the stage's figures); otherwise one line when the work starts, then at most one
every `interval` seconds (default 10 s, `SPLATTWIN_PROGRESS_INTERVAL`), and one when it ends:

    train: 1250/3000 it (42 %), 1 min 40 s, ETA 2 min 20 s, loss 0.0871, psnr 21.43, gaussians 15528
    train: 3000/3000 it done in 4 min 1 s, loss 0.0412, psnr 26.10, gaussians 43611

The ETA counts from where the run (re)started, so a resumed run does not report the checkpoint's steps as
instantaneous. Thread-safe (`update` may be called from worker callbacks).
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from typing import Any, Callable, Iterable, Iterator, TextIO, TypeVar

T = TypeVar("T")

DEFAULT_INTERVAL = 10.0   # s between plain lines
INTERVAL_ENV = "SPLATTWIN_PROGRESS_INTERVAL"


def plain_interval() -> float:
    """Seconds between plain progress lines: $SPLATTWIN_PROGRESS_INTERVAL when it is a positive number,
    else DEFAULT_INTERVAL."""
    raw = os.environ.get(INTERVAL_ENV, "")
    try:
        v = float(raw)
    except ValueError:
        return DEFAULT_INTERVAL
    return v if math.isfinite(v) and v > 0 else DEFAULT_INTERVAL


def format_duration(seconds: float) -> str:
    """'42 s', '3 min 5 s', '1 h 2 min' (seconds >= 0)."""
    s = int(round(max(seconds, 0.0)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60} min"


class Progress:
    """Progress of `total` units of work named `desc` (context manager; `close()` when not used as one).

    enabled=False: silent. stream: where to write (default sys.stderr at construction). initial: units
    already done (a resumed run). interval: s between plain lines (default `plain_interval()`). clock:
    monotonic seconds (tests pass a fake one). tty: force the terminal (True) or plain (False) form;
    default: whether the stream is a terminal.
    """

    def __init__(self, total: int | None, desc: str, unit: str = "it", enabled: bool = True,
                 initial: int = 0, stream: TextIO | None = None, interval: float | None = None,
                 clock: Callable[[], float] = time.monotonic, tty: bool | None = None):
        self.total = None if total is None else max(int(total), 0)
        self.desc, self.unit, self.enabled = desc, unit, bool(enabled)
        self.n = self.initial = max(int(initial), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.interval = plain_interval() if interval is None else float(interval)
        self.clock = clock
        self.postfix: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._t0 = clock()
        self._last = self._t0
        self._first: tuple[float, int] | None = None   # (time, count) at the first update
        self._rich = None
        self._task = None
        if not self.enabled:
            return
        is_tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else bool(tty)
        if is_tty:
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)
            from rich.progress import Progress as RichProgress

            self._rich = RichProgress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                      TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                                      TextColumn("{task.fields[post]}"),
                                      console=Console(file=self.stream, force_terminal=True), transient=False)
            self._rich.start()
            self._task = self._rich.add_task(desc, total=self.total, completed=self.n, post="")
        else:
            self._write(self._line())

    # -- updates -------------------------------------------------------------------------------------
    def update(self, n: int = 1) -> None:
        """`n` more units done. Raises KeyboardInterrupt for a Ctrl-C a library swallowed (interrupt.check)."""
        from splattwin.interrupt import check

        check()
        with self._lock:
            self.n += int(n)
            if self._first is None:   # the first unit carries the start-up (numba compiling, caches)
                self._first = (self.clock(), self.n)
            self._refresh()

    def set_postfix(self, **figures: Any) -> None:
        """Figures shown after the count (loss, psnr, ...); replaces the previous ones. Shown with the next
        line or redraw, not on their own."""
        with self._lock:
            self.postfix = dict(figures)
            if self._rich is not None:
                self._rich.update(self._task, post=self._post())

    def set_description(self, desc: str) -> None:
        with self._lock:
            self.desc = desc
            if self._rich is not None:
                self._rich.update(self._task, description=desc)

    def set_total(self, total: int | None) -> None:
        """The amount of work changed (jobs added while running)."""
        with self._lock:
            self.total = None if total is None else max(int(total), 0)
            if self._rich is not None:
                self._rich.update(self._task, total=self.total)

    def close(self, failed: bool = False) -> None:
        """End: the terminal bar stays drawn; plain output gets its final line, "done in" (a loop may end
        before `total`, e.g. on convergence) or, when `failed` (an exception left the block), "stopped
        after"."""
        with self._lock:
            if self._closed or not self.enabled:
                self._closed = True
                return
            self._closed = True
            if self._rich is not None:
                self._rich.update(self._task, completed=self.n, post=self._post())
                self._rich.stop()
            else:
                self._write(self._line(final=True, failed=failed))

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        # GeneratorExit: the consumer of `track` stopped iterating, by a break or by an exception in its loop
        # body (a Ctrl-C), which the generator cannot tell apart: "done" only when every item was done
        stopped = exc_type is not None and issubclass(exc_type, GeneratorExit) and (
            self.total is None or self.n < self.total)
        self.close(failed=exc_type is not None and (stopped or not issubclass(exc_type, GeneratorExit)))
        return False

    # -- internals -----------------------------------------------------------------------------------
    def _refresh(self) -> None:
        if not self.enabled or self._closed:
            return
        if self._rich is not None:
            self._rich.update(self._task, completed=self.n, post=self._post())
            return
        now = self.clock()
        if now - self._last >= self.interval:
            self._write(self._line(now))

    def _post(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.postfix.items())

    def _line(self, now: float | None = None, final: bool = False, failed: bool = False) -> str:
        now = self.clock() if now is None else now
        el = now - self._t0
        count = f"{self.n}/{self.total}" if self.total is not None else f"{self.n}"
        parts = [f"{self.desc}: {count} {self.unit}"]
        if final:
            parts[0] += f" {'stopped after' if failed else 'done in'} {format_duration(el)}"
        else:
            if self.total:
                parts[0] += f" ({100.0 * self.n / self.total:.0f} %)"
            parts.append(format_duration(el))
            done_here = self.n - self.initial
            rate = None   # seconds per unit
            if self._first is not None and self.n > self._first[1] and now > self._first[0]:
                # the rate since the first unit: a first training step of a minute (numba compiling on a
                # fresh cache) made the ETA of a 73 s run 4 h 52 min
                rate = (now - self._first[0]) / (self.n - self._first[1])
            elif done_here > 1 and el > 0:
                # the first update alone: one unit is all start-up (29 s of numba compiling read "ETA 24 h
                # 0 min" for a 5-minute training), so no ETA until a second update; a first update of
                # many units (a resumed count, a batch) still gives one
                rate = el / done_here
            if self.total is not None and rate is not None:
                parts.append("ETA " + format_duration((self.total - self.n) * rate))
        if self.postfix:
            parts.append(self._post())
        return ", ".join(parts)

    def _write(self, line: str) -> None:
        self._last = self.clock()
        try:
            self.stream.write(line + "\n")
            self.stream.flush()
        except (OSError, ValueError):   # a closed or broken log must not stop the work
            pass


def track(items: Iterable[T], desc: str, total: int | None = None, unit: str = "it", enabled: bool = True,
          **kw: Any) -> Iterator[T]:
    """Iterate over `items`, showing progress (`Progress`); total defaults to len(items) when it has one."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with Progress(total, desc, unit=unit, enabled=enabled, **kw) as bar:
        for x in items:
            yield x
            bar.update(1)
