"""ArUco fiducial of known size → metric scale and a table frame on the marker.

Detection uses OpenCV's aruco module; corners are refined by our own edge-line fit (see
`refine_corners_edges` for why). The four corners are triangulated
with the (unscaled) SfM cameras, then the marker's pose and the SfM scale are refined jointly by
minimising the corner reprojection error over all views that see it (scipy least squares, 7 parameters:
rotation vector, translation, log scale); the 1-sigma scale uncertainty comes from that fit's covariance.

Marker frame (OpenCV's convention, also used by `cv2.SOLVEPNP_IPPE_SQUARE`): origin at the marker
centre, x to the right of the printed pattern, y up the pattern, z out of the marker (towards the
cameras that see it). Corners in detection order: top-left (-h, h), top-right (h, h), bottom-right
(h, -h), bottom-left (-h, -h), h = size / 2.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.errors import InputError

log = logging.getLogger(__name__)


def marker_corners(size: float) -> np.ndarray:
    """Corners [4,3] of a square marker of side `size` (m) in its own frame, ArUco order."""
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def detect_marker(image: np.ndarray, dictionary: str = "DICT_4X4_50", marker_id: int = 0) -> np.ndarray | None:
    """Find one ArUco marker. image: HxWx3 float [0,1] or uint8. Returns corners [4,2] pixels or None.

    Pixel convention of `splattwin.capture.Camera` (pixel i spans [i, i+1)): OpenCV's output + 0.5.
    Corners are refined by `refine_corners_edges` (OpenCV's sub-pixel refinement is biased inwards on
    simple L-corners: markers came out ~2 % small on our renders, which is a 2 % scale error).
    """
    import cv2

    d = getattr(cv2.aruco, dictionary, None)
    if d is None or not dictionary.startswith("DICT_"):
        raise InputError(f"unknown ArUco dictionary {dictionary!r} (e.g. DICT_4X4_50, DICT_5X5_100, DICT_APRILTAG_36h11)")
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).round().astype(np.uint8)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(d), params)
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None:
        return None
    for c, i in zip(corners, ids.ravel()):
        if int(i) == int(marker_id):
            return refine_corners_edges(gray.astype(np.float64), c.reshape(4, 2).astype(np.float64) + 0.5)
    return None


def refine_corners_edges(gray: np.ndarray, corners: np.ndarray, iters: int = 3, half: float = 2.5) -> np.ndarray:
    """Sub-pixel marker corners as intersections of the four outer edges.

    Each side is sampled across its middle 70 %; along the outward normal the intensity profile (bilinear)
    crosses the mid-level between the local black border and the white quiet zone exactly at the edge for
    an area-sampled (anti-aliased) or point-sampled step edge; a line is fitted through these crossings and
    adjacent lines are intersected. gray: [H,W] float; corners: [4,2] (Camera pixel convention).
    Returns refined corners [4,2]; the input corners when an edge has too little contrast.
    """
    from scipy.ndimage import map_coordinates

    c = np.asarray(corners, dtype=np.float64).copy()
    s = np.arange(-half, half + 1e-9, 0.1)
    for _ in range(iters):
        lines = []
        centre = c.mean(0)
        for k in range(4):
            a, b = c[k], c[(k + 1) % 4]
            length = float(np.linalg.norm(b - a))
            d = (b - a) / length
            n = np.array([d[1], -d[0]])
            if n @ ((a + b) / 2 - centre) < 0:
                n = -n  # outward: from the black border into the white quiet zone
            ts = np.linspace(0.15, 0.85, max(8, int(length * 0.7)))
            P = a + ts[:, None] * (b - a)                                  # [T,2]
            Q = P[:, None, :] + s[None, :, None] * n                       # [T,S,2]
            prof = map_coordinates(gray, [Q[..., 1] - 0.5, Q[..., 0] - 0.5], order=1, mode="nearest")
            pts = []
            for i in range(len(ts)):
                pr = prof[i]
                black, white = np.median(pr[s < -half + 1]), np.median(pr[s > half - 1])
                if white - black < 20:
                    continue
                mid = 0.5 * (black + white)
                j = np.flatnonzero((pr[:-1] < mid) & (pr[1:] >= mid))
                if len(j) != 1:  # noisy or cut by something: skip this sample
                    continue
                j = j[0]
                f = (mid - pr[j]) / (pr[j + 1] - pr[j])
                pts.append(P[i] + (s[j] + f * (s[1] - s[0])) * n)
            if len(pts) < 3:
                return np.asarray(corners, dtype=np.float64)
            pts = np.asarray(pts)
            mu = pts.mean(0)
            _, _, Vt = np.linalg.svd(pts - mu)
            lines.append((mu, Vt[0]))
        new = []
        for k in range(4):
            (p1, d1), (p2, d2) = lines[(k - 1) % 4], lines[k]
            t = np.linalg.solve(np.array([d1, -d2]).T, p2 - p1)
            new.append(p1 + t[0] * d1)
        c = np.asarray(new)
    return c


def _undistort(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels [N,2] -> ideal pinhole pixels with the same K."""
    if cam.dist is None:
        return uv
    import cv2

    # Same K and pixel convention in and out, so the half-pixel convention offset cancels.
    return cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K).reshape(-1, 2)


def triangulate(cams: list[Camera], uvs: list[np.ndarray]) -> np.ndarray:
    """Linear N-view triangulation (DLT). cams: C cameras; uvs: C arrays [P,2] of ideal pixels.
    Returns points [P,3] in the cameras' world frame."""
    P = [c.K @ c.T_cam_world[:3, :] for c in cams]
    n = uvs[0].shape[0]
    out = np.zeros((n, 3))
    for j in range(n):
        A = []
        for Pm, uv in zip(P, uvs):
            u, v = uv[j]
            A.append(u * Pm[2] - Pm[0])
            A.append(v * Pm[2] - Pm[1])
        _, _, Vt = np.linalg.svd(np.asarray(A))
        X = Vt[-1]
        out[j] = X[:3] / X[3]
    return out


@dataclass
class MarkerFit:
    """Marker pose in the SfM frame and the SfM-to-metric scale.

    S_sfm_marker: [4,4] similarity, metric marker frame -> SfM frame (s * R, t); scale = s (SfM units per m).
    views: names of the views used. reproj_rms: px. scale_uncertainty_rel: 1-sigma.
    side_lengths: the four triangulated side lengths (m, after scaling) for a sanity check.
    """

    S_sfm_marker: np.ndarray
    scale: float
    views: list[str]
    reproj_rms: float
    scale_uncertainty_rel: float
    side_lengths: np.ndarray = field(default_factory=lambda: np.zeros(4))


def fit_marker(cameras: list[Camera], images: list[np.ndarray], size: float, dictionary: str = "DICT_4X4_50",
               marker_id: int = 0, where: Path | None = None, pixel_sigma_floor: float = 0.0) -> MarkerFit:
    """Detect the marker in every image, triangulate and refine (see module docstring).

    cameras: SfM cameras (any common frame and scale); images: matching HxWx3 images; size: side in metres.
    pixel_sigma_floor: lower bound (px) on the noise level used for the uncertainty; pass the SfM mean
      reprojection error: the fit holds the cameras fixed, so their own errors (which dominate: 0.5 % scale
      error with SfM cameras vs 0.03 % with exact ones on the embedded scene) would otherwise be ignored.
    Raises InputError when fewer than 2 views see it.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from splattwin.poses.align import umeyama

    if not size > 0:
        raise InputError(f"marker size must be positive (metres), got {size}")
    obs: list[tuple[Camera, np.ndarray]] = []
    for cam, img in zip(cameras, images):
        c = detect_marker(img, dictionary, marker_id)
        if c is not None:
            obs.append((cam, _undistort(cam, c)))
    if len(obs) < 2:
        raise InputError(f"ArUco marker {dictionary} id {marker_id} found in {len(obs)} registered view(s); "
                         f"need >= 2 (check --marker-dict/--marker-id, print it larger, or keep it in view)", where)
    cams = [o[0] for o in obs]
    uvs = [o[1] for o in obs]
    X = triangulate(cams, uvs)
    model = marker_corners(size)
    init = umeyama(model, X)
    s0 = init.scale
    R0 = init.S[:3, :3] / s0
    x0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), init.S[:3, 3], [np.log(s0)]])

    def residual(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        Xw = np.exp(x[6]) * model @ R.T + x[3:6]
        r = []
        for cam, uv in zip(cams, uvs):
            pc = Xw @ cam.T_cam_world[:3, :3].T + cam.T_cam_world[:3, 3]
            proj = pc[:, :2] / pc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
            r.append((proj - uv).ravel())
        return np.concatenate(r)

    sol = least_squares(residual, x0, method="lm")
    r = sol.fun
    dof = max(r.size - 7, 1)
    sigma2 = max(float(r @ r / dof), pixel_sigma_floor ** 2)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * sigma2
        unc = float(np.sqrt(max(cov[6, 6], 0.0)))  # d(log s) = ds / s
    except np.linalg.LinAlgError:
        unc = float("nan")
    s = float(np.exp(sol.x[6]))
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = sol.x[3:6]
    # Marker must face the cameras that see it (else the corner order or a mirror is wrong).
    centres = np.array([c.center for c in cams])
    if np.mean((centres - S[:3, 3]) @ R[:, 2]) <= 0:
        raise InputError("the marker's normal points away from the cameras that see it; "
                         "the reconstruction may be mirrored", where)
    Xs = X / s
    sides = np.linalg.norm(Xs - np.roll(Xs, -1, axis=0), axis=1)
    # A floor on the uncertainty: corner localisation bias (~0.1 px) is not in the fit residuals.
    f = np.mean([c.fx for c in cams])
    depth = np.mean([np.linalg.norm(c.center - S[:3, 3]) for c in cams]) / s
    floor = 0.1 * depth / f / size / np.sqrt(len(cams))
    return MarkerFit(S_sfm_marker=S, scale=s, views=[c.name for c in cams], reproj_rms=float(np.sqrt(np.mean(r ** 2))),
                     scale_uncertainty_rel=float(np.hypot(unc, floor)), side_lengths=sides)
