from __future__ import annotations

import warnings

import pytest

from splattwin import cli
from splattwin.geometry.convert import ObjectUnusableWarning


def test_our_warnings_print_as_log_lines_and_others_stay_pythons(monkeypatch, capsys):
    """During a command, a warning about the user's data reads like the log lines around it (no source
    path, no code line); library warnings keep Python's form; -v keeps ours in full."""
    def command(args):
        warnings.warn(ObjectUnusableWarning("object 'yellow_cube': too few points after cleaning (0 < 50)"))
        warnings.warn(RuntimeWarning("overflow in exp"))
        return 0

    monkeypatch.setattr(cli, "build_parser", lambda: _parser(command))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        monkeypatch.setattr(warnings, "showwarning", _stderr_show)
        assert cli.main(["go"]) == 0
        err = capsys.readouterr().err
        assert ("WARNING splattwin.geometry.convert: object 'yellow_cube': too few points after cleaning (0 < 50)\n"
                in err)
        assert "ObjectUnusableWarning" not in err and "warnings.warn(ObjectUnusable" not in err
        assert "RuntimeWarning: overflow in exp" in err and "test_cli.py" in err   # Python's form
        assert warnings.formatwarning is cli._PLAIN_FORMAT                         # restored
        assert cli.main(["-v", "go"]) == 0
        assert "ObjectUnusableWarning: object 'yellow_cube'" in capsys.readouterr().err


def _stderr_show(message, category, filename, lineno, file=None, line=None):
    import sys

    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _parser(command):
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("-v", "--verbose", action="store_true")
    p.add_argument("--debug", action="store_true")
    sub = p.add_subparsers()
    sub.add_parser("go").set_defaults(func=command)
    return p


@pytest.fixture(autouse=True)
def _keep_logging(monkeypatch):
    monkeypatch.setattr(cli.runtime, "configure", lambda: None)


# commands that finish in about a second on any input: no progress to silence
_QUICK = {("capture", "convert"), ("export",), ("report",), ("view",)}
# the others, each with a command line of its required arguments
_LONG_RUNNING = {
    ("build",): ["build", "cap", "--out", "o"],
    ("demo",): ["demo"],
    ("scene", "generate"): ["scene", "generate", "o"],
    ("capture", "info"): ["capture", "info", "v.mp4"],
    ("capture", "frames"): ["capture", "frames", "v.mp4", "o"],
    ("poses",): ["poses", "cap", "o"],
    ("train",): ["train", "cap", "o"],
    ("eval",): ["eval", "o", "--dataset", "cap"],
    ("segment",): ["segment", "cap", "--prompt", "box"],
    ("fuse",): ["fuse", "--splats", "s.ply", "--dataset", "cap", "--masks", "m", "--out", "o"],
    ("geometry",): ["geometry", "s.ply", "--out", "o"],
    ("sweep",): ["sweep", "twin", "--out", "o", "--kappa", "1"],
    ("batch",): ["batch", "cap", "--out", "o"],
    ("plan",): ["plan", "twin"],
    ("render",): ["render", "twin", "--out", "v.mp4"],
}


def _leaf_commands(parser, prefix=()):
    import argparse

    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                yield from _leaf_commands(sub, prefix + (name,))
            return
    yield prefix


def test_every_long_running_command_takes_no_progress():
    """Every command that draws progress accepts --no-progress and it turns progress off (audit 9 F2:
    fuse, geometry, plan, render, segment and sweep had no such flag). A new command must be listed here
    as quick or long-running."""
    parser = cli.build_parser()
    assert set(_leaf_commands(parser)) == _QUICK | set(_LONG_RUNNING)
    for name, argv in _LONG_RUNNING.items():
        on, off = vars(parser.parse_args(argv)), vars(parser.parse_args(argv + ["--no-progress"]))
        # `poses`/`train` take it as their options' run-time field ("@progress", absent unless given)
        assert on.get("progress", on.get("@progress", True)) is True, name
        assert off.get("progress", off.get("@progress")) is False, name


def test_every_argument_of_every_command_has_help():
    """`splattwin <command> --help` describes every argument and option (`demo --out` read bare `--out OUT`)."""
    import argparse

    from splattwin.cli import build_parser

    def bare(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    yield from bare(sub, path + [name])
            elif not isinstance(a, argparse._HelpAction) and not a.help:
                yield f"{' '.join(path)} {a.option_strings or a.dest}"

    assert not list(bare(build_parser(), ["splattwin"]))


def test_input_help_names_every_capture_layout():
    """Every command that takes a capture reads the BOP and TUM layouts too: `capture info --help` and `batch
    --help` did not say so (a robotics user with a BOP scene or a TUM pose list was told it is not read)."""
    import argparse

    from splattwin.cli import build_parser

    def positional(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    yield from positional(sub, path + [name])
            elif not a.option_strings and a.dest != "out" and a.help and "COLMAP" in a.help:
                yield " ".join(path), " ".join(a.help.split())

    helps = dict(positional(build_parser(), []))
    assert {"capture info", "batch", "build", "poses"} <= set(helps)
    for command, text in helps.items():
        assert "BOP" in text and "TUM" in text, (command, text)


def test_the_command_quiets_toppra_the_library_does_not(tmp_path):
    """TOPP-RA logs every solver step; the command sets its logger to WARNING (the robot stage did, on every
    call, overriding a library caller's own setting: audit 10A L7)."""
    import logging

    lg = logging.getLogger("toppra")
    before = lg.level
    try:
        lg.setLevel(logging.NOTSET)
        assert cli.main(["export", str(tmp_path / "no_twin")]) == 2   # bad input: exits after the logging set-up
        assert lg.level == logging.WARNING
    finally:
        lg.setLevel(before)
