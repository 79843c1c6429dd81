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
