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

SIGTERM (docker stop, Kubernetes and Slurm preemption, systemd, `timeout`) is the polite stop of a run
nobody is watching: the CLI treats it as a Ctrl-C (training finishes its step and saves a checkpoint;
a second one stops at once) and exits 143 (`exit_code`). Importing pycolmap installs glog's
failure-signal handler for SIGTERM, which printed a 30-line C stack trace and killed the process with
no checkpoint: a native library replacing our handler is undone by `check()` and `DeferredInterrupt`,
which install it again (Python still reports its own handler, so it cannot tell: they always do).
"""

from __future__ import annotations

import logging
import signal
import threading

log = logging.getLogger(__name__)

_seen = False   # a SIGINT or SIGTERM arrived since `install()` (this process)
_deferred = False   # one arrived inside a `DeferredInterrupt` (which handles it without setting _seen)
_signal = signal.SIGINT   # the last one that did: the exit code and message (`exit_code`, `message`)


def _remembering_handler(signum, frame) -> None:
    global _seen, _signal
    _seen, _signal = True, signum
    raise KeyboardInterrupt


def _ours(signum) -> bool:
    """Whether the CLI's handler may take `signum` (main thread; Python's default handling, or ours)."""
    default = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
    return threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signum) in (default, _remembering_handler)


def install() -> None:
    """The CLI's SIGINT and SIGTERM handler (main thread, when the signal has Python's default handling):
    raises KeyboardInterrupt as SIGINT's default does, and remembers the signal for `check()`/`seen()`/
    `exit_code()`. A SIGTERM someone set to be ignored (nohup-like wrappers) stays ignored. Resets the memory."""
    global _seen, _signal, _deferred
    _seen, _signal, _deferred = False, signal.SIGINT, False
    for signum in (signal.SIGINT, signal.SIGTERM):
        if _ours(signum):
            signal.signal(signum, _remembering_handler)


def uninstall() -> None:
    if signal.getsignal(signal.SIGINT) is _remembering_handler:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGTERM) is _remembering_handler:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _reclaim_sigterm() -> None:
    """Install the CLI's SIGTERM handler again where the CLI installed it: a native library imported since
    (pycolmap: glog's failure-signal handler) may have replaced it at the C level, which Python's
    `getsignal` does not show. Main thread only (Python allows `signal.signal` nowhere else)."""
    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGTERM) is _remembering_handler:
        signal.signal(signal.SIGTERM, _remembering_handler)


def seen() -> bool:
    """Whether a Ctrl-C (or SIGTERM) arrived since `install()`, whether or not it was handled."""
    return _seen


def stop_requested() -> bool:
    """Whether this process was asked to stop (a SIGINT or SIGTERM since `install()`), handled at once or
    deferred by a `DeferredInterrupt` loop."""
    return _seen or _deferred


def exit_code() -> int:
    """The CLI's exit code for the interrupt: 128 + the signal (130 for Ctrl-C, 143 for SIGTERM)."""
    return 128 + int(_signal)


def message() -> str:
    """The CLI's one line for the interrupt."""
    return "terminated (SIGTERM)" if _signal == signal.SIGTERM else "interrupted"


def check() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C arrived that nobody acted on (see the module docstring); only
    in the main thread, where Python delivers it too (a loop that defers it, `DeferredInterrupt`, has
    its own handler meanwhile). Also takes SIGTERM back from a native library (`_reclaim_sigterm`)."""
    if threading.current_thread() is not threading.main_thread():
        return
    _reclaim_sigterm()
    if _seen:
        raise KeyboardInterrupt


class DeferredInterrupt:
    """Within the block, the first SIGINT sets `requested` instead of raising; the second raises
    KeyboardInterrupt at once. Outside the main thread, or when someone else handles SIGINT, it does
    nothing (Ctrl-C raises as usual) and `requested` stays False. SIGTERM likewise, where the CLI handles
    it (`install`; a library caller's process keeps its own SIGTERM behaviour)."""

    def __init__(self, what: str = "the current step"):
        self.what = what
        self.requested = False
        self._previous: dict[int, object] = {}

    def __enter__(self) -> "DeferredInterrupt":
        if _ours(signal.SIGINT):
            self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._handle)
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGTERM) is _remembering_handler:
            # installed again even so: glog's handler (pycolmap, imported since `install`) may hold it
            self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        global _signal, _deferred
        _signal, _deferred = signum, True
        if self.requested:           # a second Ctrl-C (or SIGTERM): now
            raise KeyboardInterrupt
        self.requested = True
        if signum == signal.SIGTERM:
            log.warning("SIGTERM: stopping after %s (a second SIGTERM stops at once)", self.what)
        else:
            log.warning("interrupt: stopping after %s (Ctrl-C again to stop at once)", self.what)

    def __exit__(self, *exc) -> bool:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous = {}
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
