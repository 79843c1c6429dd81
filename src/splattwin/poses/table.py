"""Table frame from the sparse points: RANSAC plane → z up (towards the cameras), table top at z = 0.

Plane fitting is a small seeded numpy RANSAC followed by a least-squares refit on the inliers. (Open3D's
`segment_plane` runs its trials in parallel and is not reproducible even with a seed: the frame of a
resumed run would move.)
The frame: z = plane normal oriented towards the cameras; origin = centre of the inliers' extent in the
plane (robust 2nd–98th percentiles), i.e. roughly the table centre; x = the inliers' principal axis
(the table's long side), signed to agree with the first camera's image x axis for determinism.

Scale comes from a user-given known length (`KnownLength`):
- "camera_height": the mean height of the cameras above the table (or of one named image), in metres;
- "baseline": the distance between the centres of two named images, in metres (e.g. measured with the
  robot or a tape between two shots).
The reported uncertainty covers the reconstruction side only (plane-fit scatter, SfM centre noise); add
the user's own measurement error to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.errors import InputError


@dataclass
class KnownLength:
    """A user-given length in metres. kind: "camera_height" | "baseline"; images: names it refers to
    (camera_height: none = mean over all cameras, or one image; baseline: exactly two images)."""

    kind: str
    value: float
    images: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> "KnownLength":
        """Parse 'camera_height=0.55', 'camera_height@IMG=0.55' or 'baseline@IMG_A,IMG_B=0.20'."""
        try:
            lhs, val = text.split("=", 1)
            value = float(val)
        except ValueError as e:
            raise InputError(f"--known-length {text!r}: expected KIND[@IMAGES]=METRES, e.g. camera_height=0.6 "
                             f"or baseline@img_000,img_005=0.25") from e
        kind, _, imgs = lhs.partition("@")
        images = tuple(s for s in imgs.split(",") if s) if imgs else ()
        kl = cls(kind=kind.strip(), value=value, images=images)
        kl.validate()
        return kl

    def validate(self) -> None:
        if self.kind not in ("camera_height", "baseline"):
            raise InputError(f"known length kind {self.kind!r}: use camera_height or baseline")
        if not (np.isfinite(self.value) and self.value > 0):
            raise InputError(f"known length must be a positive number of metres, got {self.value}")
        from splattwin.poses.options import check_length_m

        check_length_m(self.value, "--known-length")
        if self.kind == "baseline" and len(self.images) != 2:
            raise InputError("baseline needs exactly two images: baseline@IMG_A,IMG_B=METRES")
        if self.kind == "camera_height" and len(self.images) > 1:
            raise InputError("camera_height takes at most one image: camera_height[@IMG]=METRES")


@dataclass
class PlaneFit:
    """Plane n·x + d = 0 in the input frame; n [3] unit, towards the cameras. inliers: [N] bool.
    rms: inlier distance RMS (input units)."""

    normal: np.ndarray
    d: float
    inliers: np.ndarray
    rms: float

    def share_above(self, points: np.ndarray) -> float:
        """Share of `points` [N,3] on the normal's side of the plane (the cameras above a table)."""
        return float(np.mean(np.asarray(points) @ self.normal + self.d > 0))


def plane_threshold(points: np.ndarray) -> float:
    """Default inlier distance for a plane through `points` [N,3]: 1 % of their robust (5-95 %) extent."""
    lo, hi = np.percentile(points, [5, 95], axis=0)
    return 0.01 * float(np.linalg.norm(hi - lo))


def fit_table_plane(points: np.ndarray, camera_centres: np.ndarray, threshold: float | None = None,
                    seed: int = 0, num_iterations: int = 2000, up_hint: np.ndarray | None = None,
                    max_tilt_deg: float = 90.0, min_inlier_frac: float = 0.15) -> PlaneFit:
    """RANSAC plane through the dominant flat surface of `points` [N,3]; normal oriented to the cameras.

    threshold: inlier distance; default 1 % of the points' robust extent (units of the input).
    up_hint [3], max_tilt_deg: only planes whose normal is within max_tilt_deg of +-up_hint count (the
    dominant horizontal plane, not a wall). min_inlier_frac: InputError when the best plane holds fewer
    of the points.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 20:
        raise InputError(f"only {len(pts)} sparse points: too few to find the table plane")
    if threshold is None:
        threshold = plane_threshold(pts)
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, len(pts), size=(num_iterations, 3))
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    nrm = np.cross(b - a, c - a)                                   # [I,3]
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-12
    nrm, a = nrm[ok] / ln[ok, None], a[ok]
    if up_hint is not None:
        up = np.asarray(up_hint, dtype=np.float64) / np.linalg.norm(up_hint)
        keep = np.abs(nrm @ up) >= np.cos(np.radians(max_tilt_deg))
        nrm, a = nrm[keep], a[keep]
        if not len(nrm):
            raise InputError(f"no plane within {max_tilt_deg:g} degrees of the given up direction")
    best, best_count = None, -1
    for start in range(0, len(nrm), 256):                          # chunks keep memory at [256,N]
        n_, a_ = nrm[start:start + 256], a[start:start + 256]
        dist = np.abs(pts @ n_.T - np.sum(n_ * a_, axis=1)).T          # [chunk,N] point-plane distances
        counts = (dist < threshold).sum(1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best = int(counts[k]), dist[k] < threshold
    inl = best
    # Least-squares refit on the inliers (RANSAC's normal comes from 3 points).
    q = pts[inl]
    mu = q.mean(0)
    _, _, Vt = np.linalg.svd(q - mu, full_matrices=False)
    n = Vt[2]
    if np.mean((np.asarray(camera_centres) - mu) @ n) < 0:
        n = -n
    d = -float(n @ mu)
    rms = float(np.sqrt(np.mean(((q @ n) + d) ** 2)))
    if inl.sum() < min_inlier_frac * len(pts):
        raise InputError(f"no dominant table plane: the best plane holds only {inl.sum()}/{len(pts)} points")
    return PlaneFit(normal=n, d=d, inliers=inl, rms=rms)


def table_frame(plane: PlaneFit, points: np.ndarray, first_cam: Camera) -> np.ndarray:
    """T_in_table [4,4]: rigid transform from the input frame to the table frame (z up, table at z = 0)."""
    z = plane.normal
    q = np.asarray(points)[plane.inliers]
    q_plane = q - np.outer(q @ z + plane.d, z)
    mu = q_plane.mean(0)
    _, _, Vt = np.linalg.svd(q_plane - mu, full_matrices=False)
    x = Vt[0] - (Vt[0] @ z) * z
    x /= np.linalg.norm(x)
    if x @ first_cam.T_world_cam[:3, 0] < 0:
        x = -x
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)   # columns: table axes in the input frame
    # Origin: centre of the robust in-plane extent.
    uv = (q_plane - mu) @ R[:, :2]
    lo, hi = np.percentile(uv, [2, 98], axis=0)
    origin = mu + R[:, :2] @ ((lo + hi) / 2)
    T_in_table = np.eye(4)
    T_in_table[:3, :3] = R
    T_in_table[:3, 3] = origin
    return np.linalg.inv(T_in_table)


def scale_from_known_length(known: KnownLength, cameras: dict[str, Camera], plane_rms: float,
                            mean_reproj_px: float) -> tuple[float, float, str]:
    """Metres per unit of the (table-aligned, unscaled) frame, its 1-sigma relative uncertainty, and a note.

    cameras: name -> Camera already in the table frame (unscaled: table at z = 0, z up).
    """
    def find(name: str) -> Camera:
        for key, cam in cameras.items():
            if name in (key, cam.name) or name == key.rsplit("/", 1)[-1] or name == key.rsplit("/", 1)[-1].rsplit(".", 1)[0]:
                return cam
        raise InputError(f"known length refers to image {name!r}, which is not among the registered images")

    if known.kind == "camera_height":
        cams = [find(known.images[0])] if known.images else list(cameras.values())
        h = np.array([c.center[2] for c in cams])
        if np.any(h <= 0):
            raise InputError("a camera lies below the table plane; camera_height cannot be used")
        measured = float(h.mean())
        # Plane-fit scatter plus SfM centre noise (~ reprojection error x depth / f per camera).
        f = float(np.mean([c.fx for c in cams]))
        unc = np.hypot(plane_rms / measured, max(mean_reproj_px, 0.1) / f) / np.sqrt(len(h))
        note = f"mean camera height above the table over {len(h)} camera(s)"
    else:
        a, b = find(known.images[0]), find(known.images[1])
        measured = float(np.linalg.norm(a.center - b.center))
        if measured <= 0:
            raise InputError("the two images of the baseline have the same camera centre")
        f = 0.5 * (a.fx + b.fx)
        depth = 0.5 * (a.center[2] + b.center[2])
        # Centre noise ~ reprojection error * depth / f per camera, two cameras.
        unc = np.sqrt(2.0) * max(mean_reproj_px, 0.1) * abs(depth) / f / measured
        note = f"distance between the centres of {known.images[0]} and {known.images[1]}"
    return known.value / measured, float(unc), note


# A tabletop capture's typical distance from the camera to what it sees (m): the embedded scene's cameras
# stand 0.65-0.80 m from the table centre and their median view depth is 0.67 m (measured with
# `nominal_metre` on its true poses and area-sampled surfaces); hand-held phone captures of a tabletop object
# are in the same range. Only the unscaled thresholds depend on it, never a metric twin.
NOMINAL_VIEW_DEPTH = 0.7


def nominal_metre(cameras, points: np.ndarray, view_depth: float = NOMINAL_VIEW_DEPTH,
                  max_points: int = 20000, seed: int = 0) -> float | None:
    """Frame units standing for one metre in an unscaled frame: the median over cameras of the median
    depth of the points each sees (in front, inside the image), divided by `view_depth` (m). Scales with
    the frame (twice the units, twice the value) and ignores far background the cameras do not look at
    (sky, trees: depth medians, not the points' extent). None with fewer than 2 cameras seeing >= 10
    points. cameras: Camera list (any frame); points [N,3] in the same frame."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    depth = viewing_depth(cameras, pts, min_cameras=2)
    if depth is None:
        return None
    value = depth / view_depth
    return value if np.isfinite(value) and value > 0 else None


def viewing_depth(cameras, points: np.ndarray, min_cameras: int = 1) -> float | None:
    """The median over cameras of the median depth (frame units) of the points [N,3] each sees (in
    front, inside the image; a camera counts with >= 10 of them). None with fewer than `min_cameras`."""
    depths = []
    for cam in cameras:
        uv, z = cam.project(points)
        seen = cam.in_image(uv) & (z > 0)
        if seen.sum() >= 10:
            depths.append(float(np.median(z[seen])))
    return float(np.median(depths)) if len(depths) >= max(min_cameras, 1) else None
