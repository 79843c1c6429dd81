"""Errors users can act on.

`InputError` is raised for bad input (missing or malformed files, inconsistent data). It always names the
file (or option) and the problem; the CLI turns it into a one-line message and exit code 2.
`StoppedFromOutside` is raised when something outside splattwin stopped part of a run (a worker process
killed by a signal this process did not get): the CLI prints its one line and exits with code 1.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: names what is wrong and where. The CLI exits with code 2."""

    def __init__(self, problem: str, path: str | Path | None = None):
        self.problem = problem
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class StoppedFromOutside(Exception):
    """Another process (or the job scheduler) stopped part of the run, e.g. killed a worker process with a
    signal this process did not get: not bad input and not a bug. The message names what was stopped, how,
    and how to go on. The CLI exits with code 1."""


def short_repr(v, n: int = 60) -> str:
    """repr of a value read from a file for an error message, cut to n characters: a 5000-digit number or a
    megabyte string must not fill the screen (and str() of an int of over 4300 digits raises)."""
    if isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 3 * n:
        return f"<an integer of about {int(v.bit_length() * 0.30103)} digits>"
    try:
        r = repr(v)
    except ValueError:
        return "<a value too long to print>"
    return r if len(r) <= n else r[:n - 3] + "..."


def require_type(value, types: type | tuple[type, ...], what: str, hint: str = "") -> None:
    """TypeError naming the argument and the expected type(s) when `value` is none of `types`: a library
    entry point given a path or an array where it takes an object failed deep inside with an AttributeError
    ("'str' object has no attribute 'sh_degree'"). hint: how to get the right object, e.g. "(Gaussians.load_ply)"."""
    if not isinstance(value, types):
        names = " or ".join(t.__name__ for t in (types if isinstance(types, tuple) else (types,)))
        raise TypeError(f"{what} must be a {names}{' ' + hint if hint else ''}, got {type(value).__name__}")
