"""The rich console our commands print their results through.

In a terminal it is rich's own (as wide as the window). Redirected to a file or a pipe rich would
hard-wrap every line at 80 columns, splitting paths and figures across lines (`twin: /tmp/...vi` /
`deo/twin.json`) that a log reader copies or greps; there it soft-wraps instead (a line stays one line)
and lays tables out on a wide page.

`StderrHandler` is the commands' logging handler: it writes to whatever `sys.stderr` is when a record is
emitted, so a log line during a terminal progress bar (rich swaps sys.stderr for a proxy while the bar is
live) is printed above the bar instead of being appended to the bar's line.
"""

from __future__ import annotations

import logging
import sys

from rich.console import Console

FILE_WIDTH = 200   # columns for tables written to a file or pipe


def console(stderr: bool = False) -> Console:
    """A Console on stdout (or stderr) that never hard-wraps a line when the output is not a terminal."""
    con = Console(stderr=stderr)
    if con.is_terminal:
        return con
    return Console(stderr=stderr, soft_wrap=True, width=max(con.width, FILE_WIDTH))


class StderrHandler(logging.StreamHandler):
    """A logging.StreamHandler on the current `sys.stderr`, looked up at each record. logging's own handler
    keeps the stream it was made with, so while a rich progress bar was live in a terminal its records
    bypassed rich's stderr proxy and were written onto the bar's line ("train ━━━ 0/20 ... INFO ...:
    compiling ...")."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:   # StreamHandler.__init__/setStream assign it; the lookup stays dynamic
        pass
