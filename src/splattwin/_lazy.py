"""Lazy package exports: a stage package lists its public names and the submodule of each, and nothing
is imported until a name is used (`splattwin --help` must not pay for torch, open3d or mujoco)."""

from __future__ import annotations

import importlib
import sys
from typing import Callable


def lazy_exports(package: str, exports: dict[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """Module-level `__getattr__` and `__dir__` for `package` (PEP 562).

    exports: public name -> submodule of `package` ("options") or a full module path ("splattwin.x.y")."""

    def __getattr__(name: str) -> object:
        mod = exports.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(mod if mod.startswith("splattwin.") else f"{package}.{mod}"), name)

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__
