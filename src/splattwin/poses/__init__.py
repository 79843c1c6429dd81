"""Poses stage: camera poses (SfM with pycolmap, known poses, robot poses + hand-eye) and the metric twin
frame (robot alignment, ArUco marker, table plane + known length, or flagged unscaled).

Imports are lazy: `splattwin.poses.options` is read by `splattwin --help` without numpy or pycolmap.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

_EXPORTS = {"PoseOptions": "options", "PoseResult": "estimate", "estimate_poses": "estimate",
            "load_frame": "twin_frame", "TwinFrame": "twin_frame", "KnownLength": "table"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
