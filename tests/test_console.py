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
