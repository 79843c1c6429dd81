"""The bench scripts' helpers are plain functions of their modules: tests load a script as a module by name."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture(scope="session")
def load_bench():
    """name -> the module of bench/<name>.py (loaded once per name)."""
    cache: dict = {}

    def load(name: str):
        if name not in cache:
            spec = importlib.util.spec_from_file_location(f"bench_{name}_helpers", BENCH / f"{name}.py")
            mod = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(mod)
            cache[name] = mod
        return cache[name]

    return load
