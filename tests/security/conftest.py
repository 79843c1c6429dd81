"""Fixtures of the abuse tests: a tiny posed dataset and a CLI runner that records the exit code and
stderr. Helpers (crafted files, snapshots) live in security_helpers.py, importable from the tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from splattwin.cli import main

sys.path.insert(0, str(Path(__file__).parent))

from security_helpers import CliResult  # noqa: E402

_spec = importlib.util.spec_from_file_location(
    "_security_trainer_helpers", Path(__file__).parents[1] / "splat" / "test_trainer.py")
trainer_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(trainer_helpers)


@pytest.fixture
def cli(capsys):
    """cli(*args) -> CliResult of `splattwin args...` run in this process."""
    def run(*args) -> CliResult:
        capsys.readouterr()
        rc = main([str(a) for a in args])
        cap = capsys.readouterr()
        return CliResult(rc, cap.out, cap.err)
    return run


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A nerfstudio dataset: 6 training + 1 held-out 48x36 views of a synthetic scene, with points."""
    return trainer_helpers.make_dataset(tmp_path_factory.mktemp("tiny_ds"), n_train=6, n_heldout=1)
