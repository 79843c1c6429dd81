"""Errors users can act on.

`InputError` is raised for bad input (missing or malformed files, inconsistent data). It always names the
file (or option) and the problem; the CLI turns it into a one-line message and exit code 2.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: names what is wrong and where. The CLI exits with code 2."""

    def __init__(self, problem: str, path: str | Path | None = None):
        self.problem = problem
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)
