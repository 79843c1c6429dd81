"""The rich console our commands print their results through.

In a terminal it is rich's own (as wide as the window). Redirected to a file or a pipe rich would
hard-wrap every line at 80 columns, splitting paths and figures across lines (`twin: /tmp/...vi` /
`deo/twin.json`) that a log reader copies or greps; there it soft-wraps instead (a line stays one line)
and lays tables out on a wide page.
"""

from __future__ import annotations

from rich.console import Console

FILE_WIDTH = 200   # columns for tables written to a file or pipe


def console(stderr: bool = False) -> Console:
    """A Console on stdout (or stderr) that never hard-wraps a line when the output is not a terminal."""
    con = Console(stderr=stderr)
    if con.is_terminal:
        return con
    return Console(stderr=stderr, soft_wrap=True, width=max(con.width, FILE_WIDTH))
