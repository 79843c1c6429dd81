"""Registration sanity check after SfM: images COLMAP registered but whose poses cannot be trusted.

COLMAP's relaxed retries (few 2D-3D inliers, guided matching) can register an image with a pose that fits
a handful of matches and nothing else. On the cake photos (8 phone-video frames, weak texture, wide
baselines) guided matching registered two frames from 18 and 19 observations each, mostly two-view
tracks, at the height of the table plane looking 11-13 degrees up, although their photos look down at the
plate like the other six (40 degrees down, one unit above the table). The reprojection error (0.4 px)
does not show it: a pose fitted to few points fits them well.

Checks, per registered image, in the SfM frame (any scale):
- observations: it observes fewer than `min_observations` points of the model -> its pose rests on too
  few correspondences. The default, 30, is COLMAP's own `abs_pose_min_num_inliers`, which our relaxed
  retries lower to 6 to get weak views registered at all; what they register below 30 must prove itself
  here. On the cake, a re-run of SfM (marker photos) put frame000112 57 degrees off its earlier pose from
  22 observations, within the tabletop bounds: only the count catches it;
- tabletop consistency, applied only when the capture looks like one (a dominant plane in the points, at
  least `min_cameras` cameras, and the cameras' median view pitches down at that plane by at least
  `min_median_pitch_deg`):
  - height: its centre is at less than `min_height_frac` of the median camera height above the plane (at
    or below the table), with the plane's up side chosen by the majority of the cameras;
  - pitch: it looks above the horizon while the others look down (more than `max_pitch_dev_deg` from
    their median pitch);
  - weak outlier: it observes fewer than `weak_observations` points (a pose the mapper accepted, but from
    few correspondences) AND its height or pitch is far from the others' (height off the median by more
    than `max_height_dev_frac` of it, or pitch off the median by more than `max_weak_pitch_dev_deg`). A
    well-supported image at an unusual viewpoint (a deliberate low shot) is kept; on the cake, the
    "more features" retry placed a frame from 18 observations at 0.23 x the others' height looking 2
    degrees down while the others look 31-46 degrees down;
  - view: the point the other cameras look at (least-squares point nearest their optical axes) is more
    than its half-diagonal field of view + `view_margin_deg` off its optical axis, or behind it.
Pure numpy on `Camera` objects: `splattwin.poses.sfm` runs it after each attempt and drops what it flags.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.errors import InputError


@dataclass
class SanityOptions:
    """Thresholds of `check_registration` (see the module docstring); angles in degrees."""

    min_observations: int = 30  # COLMAP's own default minimum of 2D-3D inliers to register an image
    min_cameras: int = 4
    min_height_frac: float = 0.1
    min_median_pitch_deg: float = 10.0
    max_pitch_dev_deg: float = 40.0
    view_margin_deg: float = 10.0
    weak_observations: int = 40
    max_height_dev_frac: float = 0.5
    max_weak_pitch_dev_deg: float = 25.0


@dataclass
class RegistrationCheck:
    """Verdict of `check_registration`.

    dropped: name -> why its pose is not trusted. per_image: name -> {observations, height_rel (camera
    height / median camera height above the table plane), pitch_deg (view direction below the plane's
    horizon), off_axis_deg (angle between its optical axis and the point the others look at)}; the
    geometric entries only when the tabletop check applied. tabletop: whether it applied (else `skipped`
    says why).
    """

    dropped: dict[str, str] = field(default_factory=dict)
    per_image: dict[str, dict] = field(default_factory=dict)
    tabletop: bool = False
    skipped: str = ""

    def to_dict(self) -> dict:
        return {"dropped": dict(self.dropped), "tabletop": self.tabletop, "skipped": self.skipped,
                "per_image": self.per_image}


def _axis(cam: Camera) -> np.ndarray:
    """[3] the optical axis (OpenCV +z) in the world frame."""
    return np.asarray(cam.T_world_cam[:3, 2], dtype=np.float64)


def nearest_to_axes(cams: list[Camera]) -> np.ndarray | None:
    """[3] least-squares point nearest to the optical axes, or None when they are (nearly) parallel."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        d = _axis(c)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if len(cams) < 2 or np.linalg.cond(A) > 1e6:
        return None
    return np.linalg.solve(A, b)


def _half_diagonal_fov_deg(cam: Camera) -> float:
    """Half the diagonal field of view, from the intrinsics (degrees)."""
    fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
    return float(np.degrees(np.arctan(np.hypot(cam.width / (2 * fx), cam.height / (2 * fy)))))


def check_registration(cameras: dict[str, Camera], observations: dict[str, int], points_xyz: np.ndarray,
                       opts: SanityOptions | None = None, seed: int = 0) -> RegistrationCheck:
    """Flag registered images whose poses are not trustworthy (see the module docstring).

    cameras: name -> Camera (T_world_cam, any common frame and scale). observations: name -> number of
    model points the image observes. points_xyz [N,3]: the model's points (same frame).
    Returns a RegistrationCheck; nothing is modified.
    """
    from splattwin.poses.table import fit_table_plane

    o = opts or SanityOptions()
    out = RegistrationCheck()
    for n in cameras:
        k = int(observations.get(n, 0))
        out.per_image[n] = {"observations": k}
        if k < o.min_observations:
            out.dropped[n] = (f"observes only {k} points of the model (< {o.min_observations}): its pose rests on "
                              "too few correspondences")
    names = [n for n in cameras if n not in out.dropped]
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    if len(names) < o.min_cameras:
        out.skipped = f"tabletop check needs >= {o.min_cameras} cameras, {len(names)} left"
        return out
    C = np.array([cameras[n].center for n in names])
    try:
        plane = fit_table_plane(pts, C, seed=seed)
    except InputError as e:
        out.skipped = f"no table plane: {e.problem}"
        return out
    nrm, d = plane.normal, plane.d
    if np.median(C @ nrm + d) < 0:  # up = the side most cameras are on (one wrong camera must not flip it)
        nrm, d = -nrm, -d
    # the reference (medians, the scene's look-at point) comes from the images with enough observations;
    # the geometry of the others is reported too (and added to their reason)
    every = list(cameras)
    h = {n: float(cameras[n].center @ nrm + d) for n in every}
    pitch = {n: float(np.degrees(np.arcsin(np.clip(-_axis(cameras[n]) @ nrm, -1, 1)))) for n in every}
    med_h = float(np.median([h[n] for n in names]))
    med_pitch = float(np.median([pitch[n] for n in names]))
    if med_h <= 0 or med_pitch < o.min_median_pitch_deg:
        out.skipped = (f"not a tabletop capture: median camera height {med_h:.3g}, median pitch "
                       f"{med_pitch:.1f} deg below the dominant plane's horizon")
        return out
    out.tabletop = True
    flagged: dict[str, str] = {}
    for n in every:
        rel = h[n] / med_h
        out.per_image[n].update(height_rel=round(rel, 4), pitch_deg=round(pitch[n], 2))
        if rel < o.min_height_frac:
            flagged[n] = (f"posed at or below the table plane (height {rel:.2f} x the median camera height) "
                          f"looking {abs(pitch[n]):.0f} deg {'up' if pitch[n] < 0 else 'down'}, while the "
                          f"other cameras look {med_pitch:.0f} deg down at the table from above")
        elif pitch[n] < 0 and med_pitch - pitch[n] > o.max_pitch_dev_deg:
            flagged[n] = (f"looks {-pitch[n]:.0f} deg above the horizon while the other cameras look "
                          f"{med_pitch:.0f} deg down at the table")
        elif out.per_image[n]["observations"] < o.weak_observations and (
                abs(rel - 1) > o.max_height_dev_frac or abs(pitch[n] - med_pitch) > o.max_weak_pitch_dev_deg):
            flagged[n] = (f"weakly supported ({out.per_image[n]['observations']} observations < "
                          f"{o.weak_observations}) and inconsistent with the other cameras: height {rel:.2f} x "
                          f"theirs, looking {pitch[n]:.0f} deg down where they look {med_pitch:.0f} deg down")
    # the point the (so far unflagged) cameras look at; each camera is compared with the others'
    good = [n for n in names if n not in flagged]
    for n in every:
        ref = [cameras[m] for m in good if m != n]
        target = nearest_to_axes(ref) if len(ref) >= 2 else None
        if target is None:
            continue
        ray = target - cameras[n].center
        dist = float(np.linalg.norm(ray))
        if dist <= 0:
            continue
        ang = float(np.degrees(np.arccos(np.clip(ray @ _axis(cameras[n]) / dist, -1, 1))))
        out.per_image[n]["off_axis_deg"] = round(ang, 2)
        limit = _half_diagonal_fov_deg(cameras[n]) + o.view_margin_deg
        if n not in flagged and ang > limit:
            flagged[n] = (f"looks away from the scene: the point the other cameras look at is {ang:.0f} deg off "
                          f"its optical axis (its view reaches {limit - o.view_margin_deg:.0f} deg)")
    for n, why in flagged.items():  # an image short of observations gets its geometric reason as well
        out.dropped[n] = f"{out.dropped[n]}; {why}" if n in out.dropped else why
    return out
