"""`splattwin` command line.

Each stage owns its sub-commands in `splattwin/<stage>/cli.py`, exposing `register(subparsers)`, which
adds parsers whose `func(args) -> int` runs the command. Exit codes: 0 success, 2 bad input
(`InputError`, message names the file and the problem), 1 internal error, a failed robot task or a part of
the run stopped from outside (`StoppedFromOutside`: a worker killed by someone else's signal), 130 / 143
Ctrl-C / SIGTERM (`splattwin.interrupt`).
No traceback reaches the user without `--debug`: an internal error prints one line saying what broke
and how to get the traceback for a bug report.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
import warnings
from pathlib import Path

from splattwin import __version__, runtime
from splattwin.errors import InputError, StoppedFromOutside

# Order = order in `splattwin --help`.
STAGE_CLIS = [
    "splattwin.pipeline.cli",
    "splattwin.scene.cli",
    "splattwin.capture.cli",
    "splattwin.poses.cli",
    "splattwin.splat.cli",
    "splattwin.semantics.cli",
    "splattwin.twin.geometry_cli",
    "splattwin.twin.cli",
    "splattwin.cluster.cli",
    "splattwin.playback.cli",
    "splattwin.report.cli",
    "splattwin.viewer.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="splattwin",
        description="Turn a few RGB photos of a tabletop into a planning-ready digital twin "
                    "(3D Gaussian Splatting, semantic objects, collision meshes, robot plans validated in MuJoCo).",
    )
    parser.add_argument("--version", action="version", version=f"splattwin {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of internal errors (and of bad input) for bug reports")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in STAGE_CLIS:
        importlib.import_module(mod).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command `argv` and return its exit code. With argv None (the `splattwin` program's own command
    line) a command stopped by Ctrl-C or SIGTERM ends the process at once (`_end_interrupted_process`)."""
    rc = _main(argv)
    if argv is None:
        _end_interrupted_process(rc)
    return rc


def _end_interrupted_process(rc: int) -> None:
    """End this process now with `rc` if the command was interrupted (130 / 143), skipping the interpreter's
    teardown. Why: the interrupted command has already stopped its workers, removed what it half-wrote and
    printed its line (0.05-0.2 s after the signal); what remained was Python freeing every module and object
    and the native libraries' exit handlers (pycolmap's alone 0.3-0.5 s), which at load 10 on 2 cores made
    a Ctrl-C during SfM end 0.6-6.4 s after the signal (medians per step 0.9-4.3 s), now 0.1-0.3 s. The exit
    handlers registered with `atexit` still run (logging flushes its files, temporary folders are removed,
    multiprocessing stops its children), then stdout and stderr are flushed. Not when a thread other than
    the main one (not a daemon) is still running: the ordinary exit waits for it, as it would have."""
    from splattwin import interrupt

    if not (interrupt.stop_requested() and rc == interrupt.exit_code()):
        return
    import atexit
    import os
    import threading

    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        return
    atexit._run_exitfuncs()   # what the interpreter's exit runs first (CPython's own call)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed pipe or stream: nothing more can reach it
            pass
    os._exit(rc)


def _main(argv: list[str] | None) -> int:
    runtime.configure()  # before any stage imports torch, numba or mujoco (see splattwin.runtime)
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in argv:  # accepted anywhere on the line, not only before the command
        argv = ["--debug"] + [a for a in argv if a != "--debug"]
    args, unknown = parser.parse_known_args(argv)
    if unknown:   # named by the command's own parser: its usage (`splattwin build ...`), not the top level's
        _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    from splattwin.console import StderrHandler

    # records follow sys.stderr, so one logged while a terminal progress bar is live prints above the bar
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s", handlers=[StderrHandler()])
    if not args.verbose:   # PyOpenGL (MuJoCo's renderer) logs at INFO that an optional speed-up is missing
        logging.getLogger("OpenGL").setLevel(logging.WARNING)
    # TOPP-RA logs every solver step at INFO/DEBUG (also with --verbose, as before). Set by the command, not
    # by the robot stage: a library caller's logging configuration is its own.
    logging.getLogger("toppra").setLevel(logging.WARNING)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    debug = bool(getattr(args, "debug", False))
    plain_format = warnings.formatwarning
    if not (debug or args.verbose):
        warnings.formatwarning = _format_warning
    from splattwin import interrupt

    interrupt.install()
    try:
        rc = int(args.func(args) or 0)
        if interrupt.seen():   # a Ctrl-C some library swallowed (see splattwin.interrupt): not a success
            print(interrupt.message(), file=sys.stderr)
            return interrupt.exit_code()
        return rc
    except InputError as e:
        if debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 2
    except StoppedFromOutside as e:   # not the user's input, not a bug: one line, no bug-report advice
        if debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:   # Ctrl-C (130) or SIGTERM (143): splattwin.interrupt
        print(interrupt.message(), file=sys.stderr)
        return interrupt.exit_code()
    except Exception as e:  # internal error: one line; the traceback with --debug for the bug report
        from splattwin.interrupt import is_interrupt

        if is_interrupt(e):   # Ctrl-C inside numba or torch, which wrap it (SystemError, RuntimeError)
            print(interrupt.message(), file=sys.stderr)
            return interrupt.exit_code()
        if debug:
            traceback.print_exc()
        else:
            where = _innermost_frame(e)
            print(f"internal error: {type(e).__name__}: {str(e)[:500]}{where}\n"
                  f"This is a bug in splattwin (or an unexpected library failure), not your input. Run the "
                  f"same command with --debug for the traceback and include it in a bug report.", file=sys.stderr)
        return 1
    finally:
        warnings.formatwarning = plain_format
        interrupt.uninstall()


def _command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost sub-command parser `args` were parsed with (`capture frames`: its own), else `parser`."""
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        name = getattr(args, subs[0].dest, None) if subs else None
        if name is None or name not in subs[0].choices:
            return parser
        parser = subs[0].choices[name]


def _format_warning(message, category, filename, lineno, line=None) -> str:
    """Our own warnings (MaskWarning, ObjectUnusableWarning, ...) as the log lines around them, not
    Python's `path:line: Category: message` plus the source line: they are about the user's data, not
    our code (-v / --debug keep the full form)."""
    if category.__module__.startswith("splattwin"):
        return f"WARNING {category.__module__}: {message}\n"
    return _PLAIN_FORMAT(message, category, filename, lineno, line)


_PLAIN_FORMAT = warnings.formatwarning


def _innermost_frame(e: BaseException) -> str:
    tb = e.__traceback__
    last = None
    while tb is not None:
        last = tb
        tb = tb.tb_next
    if last is None:
        return ""
    code = last.tb_frame.f_code
    return f" (in {code.co_name}, {Path(code.co_filename).name}:{last.tb_lineno})"


if __name__ == "__main__":
    sys.exit(main())
