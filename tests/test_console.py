from __future__ import annotations

import io

from splattwin.console import console


def test_redirected_output_keeps_long_lines_whole(monkeypatch, capsys):
    """Written to a file (capsys is not a terminal), a long path stays on one line: rich would wrap it
    at 80 columns."""
    monkeypatch.delenv("COLUMNS", raising=False)
    path = "/tmp/twins_for_the_quarterly_review/cake_capture_from_the_kitchen_table_video_frames_2026/twin.json"
    con = console()
    assert not con.is_terminal
    con.print(f"total 33 s; twin: {path}")
    out = capsys.readouterr().out
    assert out == f"total 33 s; twin: {path}\n"
    from rich.console import Console

    plain = io.StringIO()
    Console(file=plain).print(f"total 33 s; twin: {path}")
    assert plain.getvalue().count("\n") > 1   # what rich does on its own


def test_terminal_keeps_richs_console(monkeypatch):
    monkeypatch.setenv("TTY_COMPATIBLE", "1")   # rich >= 14: treat the stream as a terminal
    monkeypatch.setenv("FORCE_COLOR", "1")
    con = console()
    assert con.is_terminal and not con.soft_wrap


def test_a_record_logged_during_a_terminal_bar_is_printed_above_it(monkeypatch):
    """The commands' logging handler follows sys.stderr, which rich proxies while a terminal bar is live, so
    a record logged mid-bar gets a line of its own above the bar (logging's own handler wrote it onto the
    bar's line: 'train ━━━ 0/3 ... ETA -:--:--  INFO x: hello')."""
    import logging
    import sys

    from splattwin.console import StderrHandler
    from splattwin.progress import Progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    term = Tty()
    monkeypatch.setattr(sys, "stderr", term)
    log = logging.getLogger("splattwin.test_console")
    handler = StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    monkeypatch.setattr(log, "handlers", [handler])
    monkeypatch.setattr(log, "propagate", False)
    log.setLevel(logging.INFO)
    with Progress(3, "train", stream=term) as bar:
        bar.update(1)
        log.info("compiling the kernels")
        bar.update(2)
    out = term.getvalue()
    lines = [ln.rsplit("\r", 1)[-1] for ln in out.split("\n") if "compiling the kernels" in ln]
    assert len(lines) == 1 and "━" not in lines[0]     # its own line, not the bar's
    assert lines[0].endswith("INFO splattwin.test_console: compiling the kernels")
    assert "3/3" in out.split("compiling the kernels", 1)[1]   # the bar goes on below it


def test_the_command_logs_through_the_stderr_handler():
    """`splattwin ...` configures logging with StderrHandler (a fresh process: pytest's own handlers make
    basicConfig a no-op here)."""
    import subprocess
    import sys

    code = ("import logging, sys; from splattwin.cli import main; rc = main(['capture', 'info', '/nonexistent/x']); "
            "print(rc, [type(h).__name__ for h in logging.getLogger().handlers])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120).stdout
    assert out.strip().endswith("2 ['StderrHandler']")
