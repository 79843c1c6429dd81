"""Poses stage: camera poses (SfM with pycolmap, known poses, robot poses + hand-eye) and the metric twin
frame (robot alignment, ArUco marker, table plane + known length, or flagged unscaled)."""

from splattwin.poses.estimate import PoseOptions, PoseResult, estimate_poses, load_frame
from splattwin.poses.table import KnownLength

__all__ = ["KnownLength", "PoseOptions", "PoseResult", "estimate_poses", "load_frame"]
