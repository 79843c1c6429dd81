"""Poses stage: camera poses (SfM with pycolmap, known poses, robot poses + hand-eye) and the metric twin
frame (robot alignment, ArUco marker, table plane + known length, or flagged unscaled).

Imports are lazy: `splattwin.poses.options` is read by `splattwin --help` without numpy or pycolmap.
"""

from __future__ import annotations

import importlib

_EXPORTS = {"PoseOptions": "options", "PoseResult": "estimate", "estimate_poses": "estimate",
            "load_frame": "twin_frame", "TwinFrame": "twin_frame", "KnownLength": "table"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"splattwin.poses.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'splattwin.poses' has no attribute {name!r}")
