"""Which way is up: a sanity check of known camera poses, and the rotation that brings their world to
the twin frame (z up); and, for frames with no up of their own (SfM), which plane is the table
(`table_plane_under_cameras`: the dominant plane unless the cameras' horizon says it is a wall).

Datasets with known poses use many world conventions: z up (ROS, MuJoCo, the twin), z down (robot and
camera-like worlds), y up (OpenGL / Blender exports), or the first camera's frame (tilted). Taking any of
them as "z up" turns the twin upside down or on its side, so `check_up` looks for up in the data itself.

Cues, all in the input world frame:
- the cameras, "horizon" cue: people (and most robot wrist cameras) hold cameras with little roll, so
  every camera's image x axis is nearly horizontal and up is the direction most perpendicular to all of
  them (the eigenvector of the smallest eigenvalue of mean(x x^T); OpenSfM aligns "horizontal" captures
  the same way). Used when it is well defined (smallest eigenvalue < 0.02, middle one > 0.1: the x axes
  span a plane); its sign, and the fallback when it is not (cameras rolled every which way, or all
  facing one direction), is the mean of each camera's image-up direction (-y) plus its viewing
  direction reversed (-z), which points up for cameras looking at a table from the side down to
  straight down (strength = |mean| / sqrt(2) in [0, 1]). On the real captures (../shared/data/real,
  SfM poses) the two agree within 3 degrees for the cake; for the statue, photographed from below, the
  horizon cue says every camera is pitched up 13-18 degrees (as the photos look) while the mean is 56
  degrees away from it, hence the order.
- the table plane: a RANSAC plane (`splattwin.poses.table.fit_table_plane`) through the 3D points
  available (the dataset's points, triangulated points, back-projected depth), its normal oriented
  towards the cameras (the cameras are above the table). Precise, but only a table when most cameras
  are on one side of it.

Decision: with both cues they must agree within `MAX_CUE_ANGLE` (else the dominant plane may be a wall:
ambiguous) and up = the plane normal; with the plane only, up = its normal; with the cameras only, up =
the camera cue if it is well defined (`MIN_CAMERA_STRENGTH`); otherwise ambiguous. Then, when up is
within `AXIS_SNAP_DEG` of a world axis (+-x, +-y, +-z), that axis is the input's up and the rotation is
the exact quarter/half turn taking it to +z (identity for +z, 180 degrees about x for -z), so the twin
keeps the user's coordinates up to that recorded rotation. A world tilted away from every axis is
levelled by the smallest rotation taking up to +z, but only on the table plane: the cameras alone are
too coarse for that (a camera cue within `CAMERA_SNAP_DEG` of an axis is snapped to it; further off,
the check stops). Ambiguous captures stop with an InputError that shows the evidence and names the
override (`PoseOptions.up`, `--up`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.errors import InputError

log = logging.getLogger(__name__)

AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
        "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
UP_CHOICES = ("auto", "keep", *AXES)
AXIS_SNAP_DEG = 15.0        # up this close to a world axis: that axis is the input's up
CAMERA_SNAP_DEG = 30.0      # the same for up from the cameras alone (a coarser cue, never used to level)
MAX_CUE_ANGLE = 60.0        # camera cue and table normal further apart than this: ambiguous
MIN_CAMERA_STRENGTH = 0.5   # |mean(-y_cam - z_cam)| / sqrt(2) needed to trust the cameras alone
MIN_CAMERAS_ABOVE = 0.8     # share of cameras on the normal's side for a plane to count as the table


@dataclass
class UpCheck:
    """Where up is in the input world and what was done about it.

    up_input: [3] unit vector, up in the input world. input_up: the axis it was snapped to ("+z", "-z",
    ...), or "tilted". R_twin_input: [3,3] rotation applied to the input world (identity: none).
    source: "table_plane+cameras" | "table_plane" | "cameras" | "given". evidence: the cue numbers.
    """

    up_input: np.ndarray
    input_up: str
    R_twin_input: np.ndarray
    source: str
    evidence: dict = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return not np.allclose(self.R_twin_input, np.eye(3))

    @property
    def T_twin_input(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R_twin_input
        return T

    def describe(self) -> str:
        if not self.changed:
            return f"input world is z up (checked: {self.source})"
        how = _rotation_text(self.R_twin_input)
        return f"input world has up {self.input_up} (from {self.source}); rotated {how} to make it z up"

    def to_dict(self) -> dict:
        return {"input_up": self.input_up, "up_in_input": [float(x) for x in self.up_input],
                "source": self.source, "R_twin_input": self.R_twin_input.tolist(),
                "applied": _rotation_text(self.R_twin_input) if self.changed else "none", **self.evidence}


def _rotation_text(R: np.ndarray) -> str:
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R).as_rotvec()
    ang = float(np.linalg.norm(rv))
    if ang < 1e-9:
        return "by 0 degrees"
    axis = rv / ang
    name = next((k for k, v in AXES.items() if np.allclose(axis, v, atol=1e-6)), None)
    return f"{math.degrees(ang):.1f} degrees about {name or np.round(axis, 4).tolist()}"


def camera_cue(cameras: list[Camera]) -> tuple[np.ndarray, float, str]:
    """(unit up estimate [3], strength in [0, 1], "horizon" | "view") from the cameras (module docstring)."""
    R = np.array([c.T_world_cam[:3, :3] for c in cameras])          # [N,3,3] columns = camera axes in world
    m = (-R[:, :, 1] - R[:, :, 2]).mean(axis=0)                       # image up + backwards
    n = float(np.linalg.norm(m))
    view = m / n if n > 0 else np.array([0.0, 0.0, 1.0])
    strength = n / math.sqrt(2.0)
    x = R[:, :, 0]
    w, V = np.linalg.eigh(x.T @ x / len(x))                           # ascending eigenvalues
    if len(cameras) >= 3 and w[0] < 0.02 and w[1] > 0.1 and strength > 0.2:
        g = V[:, 0] * (1.0 if V[:, 0] @ view >= 0 else -1.0)
        return g, 1.0 - w[0] / w[1], "horizon"
    return view, strength, "view"


def axis_rotation(axis: str) -> np.ndarray:
    """[3,3] rotation taking the world axis `axis` ("+x" ... "-z") to +z by a quarter or half turn about
    x or y (the other axes stay axes)."""
    from scipy.spatial.transform import Rotation

    turn = {"+z": ("x", 0.0), "-z": ("x", 180.0), "+y": ("x", 90.0), "-y": ("x", -90.0),
            "+x": ("y", -90.0), "-x": ("y", 90.0)}[axis]
    R = Rotation.from_euler(turn[0], turn[1], degrees=True).as_matrix()
    return np.round(R, 12) + 0.0   # exact zeros and ones (no -0.0 or 6e-17 left in frame.json)


def level_rotation(up: np.ndarray) -> np.ndarray:
    """Smallest [3,3] rotation taking the unit vector `up` to +z."""
    from scipy.spatial.transform import Rotation

    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    if up[2] < -1 + 1e-12:
        return axis_rotation("-z")
    R, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])
    return R.as_matrix()


def depth_points(frames, depth_scale: float | None, max_frames: int = 12, stride: int = 8,
                 max_points: int = 60_000, seed: int = 0) -> np.ndarray:
    """[N,3] world points back-projected from the depth images of up to `max_frames` evenly spread
    frames (every `stride`-th pixel): a cheap cloud for the table plane."""
    from splattwin.capture import load_depth
    from splattwin.poses.depth import backproject_depth

    with_depth = [f for f in frames if f.depth_path is not None]
    if not with_depth:
        return np.zeros((0, 3))
    pick = np.unique(np.linspace(0, len(with_depth) - 1, min(max_frames, len(with_depth))).round().astype(int))
    xs = []
    for i in pick:
        f = with_depth[i]
        d = load_depth(f.depth_path, depth_scale, size=(f.camera.width, f.camera.height))
        xyz, _ = backproject_depth(d, f.camera, None, stride=stride)
        xs.append(xyz)
    xyz = np.concatenate(xs)
    if len(xyz) > max_points:
        xyz = xyz[np.random.default_rng(seed).choice(len(xyz), max_points, replace=False)]
    return xyz


def check_up(cameras: list[Camera], points: np.ndarray | None = None, up: str = "auto",
             where: str | Path | None = None, seed: int = 0) -> UpCheck:
    """Find up in the input world of `cameras` (and `points` [N,3], same frame) and the rotation to z up.

    up: "auto" (detect, see module docstring), or the input world's up axis ("+z", "-z", "+y", ...) to
    use as given. Raises InputError naming `where` when the cues are ambiguous.
    """
    if up not in UP_CHOICES or up == "keep":
        raise ValueError(f"up must be one of {', '.join(c for c in UP_CHOICES if c != 'keep')}, got {up!r}")
    if up in AXES:
        v = np.array(AXES[up])
        return UpCheck(up_input=v, input_up=up, R_twin_input=axis_rotation(up), source="given")
    if not cameras:
        raise InputError("no cameras to find up from", where)
    cam_up, strength, kind = camera_cue(cameras)
    ev: dict = {"camera_up": [round(float(x), 6) for x in cam_up], "camera_strength": round(strength, 4),
                "camera_cue": kind}
    normal = None
    if points is not None and len(points) >= 50:
        from splattwin.poses.table import fit_table_plane

        centres = np.array([c.center for c in cameras])
        try:
            plane = fit_table_plane(np.asarray(points, dtype=np.float64), centres, seed=seed)
        except InputError as e:
            ev["table_plane"] = f"none ({e.problem})"
        else:
            above = plane.share_above(centres)
            ev.update(table_normal=[round(float(x), 6) for x in plane.normal], cameras_above_table=round(above, 3),
                      table_inliers=int(plane.inliers.sum()), table_points=int(len(points)))
            if above >= MIN_CAMERAS_ABOVE:
                normal = plane.normal
            else:
                ev["table_plane"] = f"rejected: only {above:.0%} of the cameras are on one side of it"
    else:
        ev["table_plane"] = "none (fewer than 50 points: no point cloud or depth)"
    strong = strength >= MIN_CAMERA_STRENGTH
    if normal is not None and strong:
        ang = math.degrees(math.acos(float(np.clip(normal @ cam_up, -1.0, 1.0))))
        ev["cue_angle_deg"] = round(ang, 2)
        if ang > MAX_CUE_ANGLE:
            raise InputError(_ambiguous(f"the cameras say up is {_fmt(cam_up)} but the dominant plane's normal is "
                                        f"{_fmt(normal)} ({ang:.0f} degrees apart: is the plane a wall?)"), where)
        up_v, source = normal, "table_plane+cameras"
    elif normal is not None:
        up_v, source = normal, "table_plane"
    elif strong:
        up_v, source = cam_up, "cameras"
    else:
        raise InputError(_ambiguous(f"no table plane ({ev.get('table_plane', 'none')}) and the cameras disagree "
                                    f"about up (strength {strength:.2f} < {MIN_CAMERA_STRENGTH})"), where)
    dots = {k: float(np.dot(up_v, v)) for k, v in AXES.items()}
    best = max(dots, key=dots.get)
    off = math.degrees(math.acos(min(1.0, dots[best])))
    ev["angle_to_axis_deg"] = round(off, 3)
    if off <= (CAMERA_SNAP_DEG if source == "cameras" else AXIS_SNAP_DEG):
        return UpCheck(up_input=up_v, input_up=best, R_twin_input=axis_rotation(best), source=source, evidence=ev)
    if source == "cameras":
        raise InputError(_ambiguous(f"the cameras alone say up is {_fmt(up_v)}, {off:.0f} degrees from the nearest "
                                    f"world axis ({best}), and without a table plane (no points or depth) the world "
                                    f"cannot be levelled reliably"), where)
    log.warning("the known poses' world is tilted %.1f degrees from its nearest axis (%s): levelling it with the "
                "%s", off, best, source.replace("+", " and "))
    return UpCheck(up_input=up_v, input_up="tilted", R_twin_input=level_rotation(up_v), source=source, evidence=ev)


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:+.2f}" for x in v) + ")"


def _ambiguous(why: str) -> str:
    return (f"cannot tell which way is up in the known poses' world: {why}. Say which world axis points up "
            f"with --up=+z (or --up=-z, +y, -y, +x, -x), or --up=keep to use the poses as they are")


WALL_TILT_DEG = MAX_CUE_ANGLE   # a dominant plane this far from the cameras' horizon up is a wall
TABLE_TILT_DEG = 15.0           # the table sought instead: within this of the cameras' up (their horizon is
                                # good to a few degrees: the cake's table is 6 degrees from it)
MIN_TABLE_FRAC = 0.05           # ... holding at least this share of the points


def table_plane_under_cameras(points: np.ndarray, cameras: list[Camera], seed: int = 0):
    """(PlaneFit, evidence dict) of the table in a frame with no up of its own (SfM, unscaled poses).

    The dominant plane of `points` (`fit_table_plane`) is the table unless the cameras' horizon cue
    (`camera_cue`: their image x axes are level) is well defined and puts up more than `WALL_TILT_DEG`
    from its normal: then the dominant plane is a wall (a tabletop against a wall, a facade behind a
    statue), and the table is the largest plane within `TABLE_TILT_DEG` of the cameras' up holding
    >= `MIN_TABLE_FRAC` of the points with >= `MIN_CAMERAS_ABOVE` of the cameras above it. With no such
    plane the frame is levelled by the cameras: a plane normal to their up through the lowest points
    (2nd percentile of height), and a warning. InputError only when `fit_table_plane` finds no plane.
    """
    from splattwin.poses.table import PlaneFit, fit_table_plane, plane_threshold

    pts = np.asarray(points, dtype=np.float64)
    centres = np.array([c.center for c in cameras])
    plane = fit_table_plane(pts, centres, seed=seed)
    cam_up, strength, kind = camera_cue(cameras)
    ev: dict = {"camera_up": [round(float(x), 6) for x in cam_up], "camera_strength": round(strength, 4),
                "camera_cue": kind, "dominant_plane_normal": [round(float(x), 6) for x in plane.normal],
                "dominant_plane_inliers": int(plane.inliers.sum())}
    ang = math.degrees(math.acos(float(np.clip(abs(plane.normal @ cam_up), 0.0, 1.0))))
    ev["dominant_plane_tilt_deg"] = round(ang, 2)
    if kind != "horizon" or strength < MIN_CAMERA_STRENGTH or ang <= WALL_TILT_DEG:
        ev["table"] = "dominant plane"
        if kind == "horizon" and strength >= MIN_CAMERA_STRENGTH and ang > TABLE_TILT_DEG:
            # neither level nor a wall: a sloped surface, or a capture of something other than a tabletop
            # (the british_museum facade became the "table" at 38 degrees without a word)
            log.warning("the table plane (the dominant plane, %d points) is %.0f degrees from the cameras' up: "
                        "is this a tabletop capture? The twin's z axis follows that plane; check poses/cameras.png",
                        plane.inliers.sum(), ang)
        return plane, ev
    try:
        table = fit_table_plane(pts, centres, seed=seed, up_hint=cam_up, max_tilt_deg=TABLE_TILT_DEG,
                                min_inlier_frac=MIN_TABLE_FRAC)
        above = table.share_above(centres)
        if above < MIN_CAMERAS_ABOVE:
            raise InputError(f"only {above:.0%} of the cameras are above the level plane")
    except InputError as e:
        lo = float(np.percentile(pts @ cam_up, 2))
        dist = pts @ cam_up - lo
        near = np.abs(dist) < plane_threshold(pts)
        table = PlaneFit(normal=cam_up.copy(), d=-lo, inliers=np.ones(len(pts), bool),
                         rms=float(np.sqrt(np.mean(dist[near] ** 2))) if near.any() else 0.0)
        ev["table"] = f"none level ({e.problem}): levelled by the cameras, z = 0 at the lowest points"
        log.warning("the dominant plane (%d points) is %.0f degrees from the cameras' up: a wall, not a table; no "
                    "level plane found (%s), so the frame is levelled by the cameras' horizon, z = 0 at the lowest "
                    "points", plane.inliers.sum(), ang, e.problem)
        return table, ev
    ev.update(table="level plane under a wall", table_normal=[round(float(x), 6) for x in table.normal],
              table_inliers=int(table.inliers.sum()))
    log.warning("the dominant plane (%d points) is %.0f degrees from the cameras' up: a wall, not a table; the "
                "table frame uses the largest level plane (%d points) instead", plane.inliers.sum(), ang,
                table.inliers.sum())
    return table, ev
