"""viewer stage."""

from __future__ import annotations

import importlib

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"serve": "app", "TwinView": "splattwin.playback.view_model"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        mod = _EXPORTS[name]
        return getattr(importlib.import_module(mod if mod.startswith("splattwin.") else f"splattwin.viewer.{mod}"), name)
    raise AttributeError(f"module 'splattwin.viewer' has no attribute {name!r}")
