"""Ctrl-C during long loops: finish the step, save, stop; and an interrupt is never reported as a bug.

Why: Python raises KeyboardInterrupt wherever the main thread is when the signal arrives. In our loops
that is almost always inside a numba kernel or a torch op, which re-raise it wrapped (numba's dispatcher:
`SystemError: ... returned a result with an exception set`), so the CLI reported "internal error ... this
is a bug in splattwin" and exit 1 for a user's Ctrl-C; and it lands mid-step (after the backward pass and
before the optimiser step, or halfway through a densification), where no consistent checkpoint can be
written, so up to `checkpoint_every` steps were lost.

`DeferredInterrupt` (a context manager around a loop, main thread only) turns the first Ctrl-C into a
request the loop polls between steps (`requested`): the loop finishes the step it is in, saves its state
and raises KeyboardInterrupt itself. A second Ctrl-C stops at once, as before. `is_interrupt` finds a
KeyboardInterrupt in an exception's cause/context chain (for the CLI's exit code 130).

Some libraries swallow a KeyboardInterrupt: trimesh wraps its lazy imports (networkx, scipy) in
`except BaseException`, so a Ctrl-C landing in one was lost and the build ran to the end with exit 0.
The CLI therefore installs `install()`'s handler, which remembers every SIGINT; `check()` (between
pipeline stages and on every progress update) raises KeyboardInterrupt for one that was swallowed, and
the CLI exits 130 for it even when the command returned.
"""

from __future__ import annotations

import logging
import signal
import threading

log = logging.getLogger(__name__)

_seen = False   # a SIGINT arrived since `install()` (this process)


def _remembering_handler(signum, frame) -> None:
    global _seen
    _seen = True
    raise KeyboardInterrupt


def install() -> None:
    """The CLI's SIGINT handler (main thread, when SIGINT has Python's default handler): as the default,
    and it remembers the interrupt for `check()`/`seen()`. Resets the memory."""
    global _seen
    _seen = False
    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _remembering_handler):
        signal.signal(signal.SIGINT, _remembering_handler)


def uninstall() -> None:
    if signal.getsignal(signal.SIGINT) is _remembering_handler:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def seen() -> bool:
    """Whether a Ctrl-C arrived since `install()`, whether or not it was handled."""
    return _seen


def check() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C arrived that nobody acted on (see the module docstring); only
    in the main thread, where Python delivers it too (a loop that defers it, `DeferredInterrupt`, has
    its own handler meanwhile)."""
    if _seen and threading.current_thread() is threading.main_thread():
        raise KeyboardInterrupt


class DeferredInterrupt:
    """Within the block, the first SIGINT sets `requested` instead of raising; the second raises
    KeyboardInterrupt at once. Outside the main thread, or when someone else handles SIGINT, it does
    nothing (Ctrl-C raises as usual) and `requested` stays False."""

    def __init__(self, what: str = "the current step"):
        self.what = what
        self.requested = False
        self._previous = None
        self._installed = False

    def __enter__(self) -> "DeferredInterrupt":
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _remembering_handler):
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:           # a second Ctrl-C: now
            raise KeyboardInterrupt
        self.requested = True
        log.warning("interrupt: stopping after %s (Ctrl-C again to stop at once)", self.what)

    def __exit__(self, *exc) -> bool:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False
        return False


def is_interrupt(e: BaseException | None) -> bool:
    """Whether `e` is a KeyboardInterrupt or was raised while handling one / because of one (a library
    wrapping it: numba's SystemError, torch's RuntimeError)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False
