"""The one camera type used everywhere.

Convention: OpenCV. Camera frame x right, y down, z forward (viewing direction). `T_world_cam` maps
camera-frame points to the world frame (camera-to-world). Pixel coordinates: (u, v) = (0, 0) is the
top-left corner of the top-left pixel; pixel index (i, j) covers [i, i+1) x [j, j+1) and its centre is
(i + 0.5, j + 0.5): COLMAP's (and nerfstudio's, 3DGS's) convention, which K and `project` use. OpenCV,
ROS camera_info, BOP and TUM put pixel centres at integers (u_opencv = u_ours - 0.5), so their principal
point is cx + 0.5, cy + 0.5 here (`capture.bop`, `capture.tum` convert). Units: metres, pixels.

OpenGL / nerfstudio / Blender cameras look down -z with y up; `T_world_cam_gl` converts by flipping the
camera's y and z axes (`opencv_from_opengl`, `opengl_from_opencv`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from splattwin.equality import dataclass_eq
from splattwin.errors import InputError

# Flip of camera y and z axes: OpenCV <-> OpenGL (its own inverse).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_from_opengl(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world in the OpenGL convention (y up, looking down -z) -> OpenCV convention. [4,4]"""
    return np.asarray(T_world_cam_gl, dtype=np.float64) @ _FLIP_YZ


def opengl_from_opencv(T_world_cam: np.ndarray) -> np.ndarray:
    """Camera-to-world in the OpenCV convention -> OpenGL/nerfstudio convention. [4,4]"""
    return np.asarray(T_world_cam, dtype=np.float64) @ _FLIP_YZ


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform [4,4] (or batch [...,4,4])."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV camera-to-world pose at `eye` looking at `target`, with image 'up' towards world `up`. [4,4]"""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular x
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


@dataclass
class Camera:
    """A pinhole camera with optional OpenCV radial/tangential distortion.

    Attributes:
        K: [3,3] intrinsics (fx, fy, cx, cy in pixels).
        width, height: image size in pixels.
        T_world_cam: [4,4] camera-to-world, OpenCV convention, metres. Identity if unknown.
        dist: distortion (k1, k2, p1, p2[, k3]) or None for an ideal pinhole.
        name: image name / id (free text, e.g. the file stem).
    """

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    dist: np.ndarray | None = None
    name: str = ""

    __eq__ = dataclass_eq   # array-aware (K, pose): `cam in cameras` works (splattwin.equality)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=np.float64).reshape(4, 4)
        self.width, self.height = int(self.width), int(self.height)
        if self.dist is not None:
            self.dist = np.asarray(self.dist, dtype=np.float64).ravel()
            if self.dist.size not in (4, 5):
                raise InputError(f"camera {self.name!r}: distortion must have 4 or 5 coefficients, got {self.dist.size}")
            if not np.any(self.dist):
                self.dist = None
        self.validate()

    # -- checks -------------------------------------------------------------------------------
    def validate(self) -> None:
        where = f"camera {self.name!r}" if self.name else "camera"
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"{where}: image size must be positive, got {self.width}x{self.height}")
        if not np.all(np.isfinite(self.K)) or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise InputError(f"{where}: intrinsics must be finite with positive focal lengths")
        if np.max(np.abs(self.K[2] - [0.0, 0.0, 1.0])) > K_TOL:   # the wording of `plausible`
            raise InputError(f"{where}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (last row 0 0 1), got "
                             f"{np.array2string(self.K, precision=6, separator=', ')}".replace("\n", ""))
        if not np.all(np.isfinite(self.T_world_cam)):
            raise InputError(f"{where}: pose T_world_cam is not finite")
        if np.max(np.abs(self.T_world_cam[3] - [0.0, 0.0, 0.0, 1.0])) > 1e-6:
            raise InputError(f"{where}: pose T_world_cam must end with the row 0 0 0 1 (a rigid transform), got "
                             f"{[float(x) for x in self.T_world_cam[3]]}")
        R = self.T_world_cam[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise InputError(f"{where}: pose rotation is not a proper rotation matrix")

    # -- derived ------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def T_cam_world(self) -> np.ndarray:
        """World-to-camera [4,4] (the 'viewmat' of gsplat)."""
        return invert_se3(self.T_world_cam)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [3]."""
        return self.T_world_cam[:3, 3].copy()

    @property
    def T_world_cam_gl(self) -> np.ndarray:
        """Camera-to-world in the OpenGL/nerfstudio convention [4,4]."""
        return opengl_from_opencv(self.T_world_cam)

    @classmethod
    def from_fov(cls, fov_x: float, width: int, height: int, T_world_cam: np.ndarray | None = None,
                 name: str = "") -> "Camera":
        """Pinhole camera with horizontal field of view `fov_x` (radians), principal point at the centre."""
        f = 0.5 * width / np.tan(0.5 * fov_x)
        K = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
        return cls(K=K, width=width, height=height,
                   T_world_cam=np.eye(4) if T_world_cam is None else T_world_cam, name=name)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 halves width and height)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        return replace(self, K=K, width=w, height=h)

    # -- projection ---------------------------------------------------------------------------
    def world_to_cam(self, p_world: np.ndarray) -> np.ndarray:
        """[N,3] world points -> [N,3] camera-frame points."""
        T = self.T_cam_world
        return np.asarray(p_world, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]

    def pixel_rays(self) -> np.ndarray:
        """[H,W,3] camera-frame ray directions with z = 1 through the pixel centres (pinhole: the lens
        distortion, if any, is ignored), so that `pixel_rays() * depth[..., None]` back-projects a z-depth map."""
        v, u = np.mgrid[0:self.height, 0:self.width]
        return np.stack([(u + 0.5 - self.cx) / self.fx, (v + 0.5 - self.cy) / self.fy, np.ones(u.shape)], axis=-1)

    def project(self, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points. Returns (uv [N,2] pixels with distortion applied, depth z [N] metres).

        Points with z <= 0 get uv = nan.
        """
        p = self.world_to_cam(p_world)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = p[:, 0] / z
            y = p[:, 1] / z
        if self.dist is not None:
            x, y = distort(x, y, self.dist)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)
        uv[z <= 0] = np.nan
        return uv, z

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """[N] bool: pixel coordinates inside the sensor (finite and within [0, W) x [0, H))."""
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def to_dict(self) -> dict:
        d = {"name": self.name, "width": self.width, "height": self.height, "K": self.K.tolist(),
             "T_world_cam": self.T_world_cam.tolist()}
        if self.dist is not None:
            d["dist"] = self.dist.tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(K=np.array(d["K"]), width=d["width"], height=d["height"],
                   T_world_cam=np.array(d.get("T_world_cam", np.eye(4))), dist=d.get("dist"),
                   name=d.get("name", ""))


# Bounds on a camera read from a dataset file (`plausible`): wide enough for any real lens, narrow enough
# that a typo or a hostile file cannot give a focal length of 5e-15 px or a principal point 80 px off a 1x1
# image (both were accepted and made every later stage produce nonsense or fail far from the cause).
FOCAL_RANGE = (1e-3, 1e3)   # fx, fy as a multiple of the image's larger side (a fisheye is ~0.3, a 1° lens ~60)
MAX_DISTORTION = 1e3        # |k1 k2 p1 p2 k3| (real lenses: |k| < 10 even for the rational wide-angle fits)
K_TOL = 1e-6                # the fixed entries of K (0, 0, 1 in the last row, 0 below fx, no skew)


def plausible(cam: Camera) -> Camera:
    """`cam` if its numbers are those of a real camera, else InputError (without a path: readers wrap it
    with the file, as they do Camera's own errors): K of the form [[fx 0 cx] [0 fy cy] [0 0 1]] (other
    entries would be silently dropped), fx, fy within FOCAL_RANGE x the image's larger side, the principal
    point within [-w, 2w] x [-h, 2h], distortion within +-MAX_DISTORTION, and the camera centre within
    +-MAX_POSITION metres (`splattwin.limits`)."""
    from splattwin.limits import MAX_POSITION

    where = f"camera {cam.name!r}: " if cam.name else ""
    K, w, h = cam.K, cam.width, cam.height
    fixed = [K[1, 0], K[2, 0], K[2, 1], K[2, 2] - 1.0, K[0, 1] / max(abs(K[0, 0]), 1.0)]
    if max(abs(x) for x in fixed) > K_TOL:
        raise InputError(f"{where}K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew; last row 0 0 1), got "
                         f"{np.array2string(K, precision=6, separator=', ')}".replace("\n", ""))
    lo, hi = (r * max(w, h) for r in FOCAL_RANGE)
    for name, f in (("fx", cam.fx), ("fy", cam.fy)):
        if not lo <= f <= hi:
            raise InputError(f"{where}focal length {name} = {f:g} px is implausible for a {w}x{h} image (expected "
                             f"{FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} x its larger side: {lo:g} to {hi:g} px)")
    if not (-w <= cam.cx <= 2 * w and -h <= cam.cy <= 2 * h):
        raise InputError(f"{where}principal point (cx, cy) = ({cam.cx:g}, {cam.cy:g}) is far outside the {w}x{h} "
                         f"image (expected cx in [{-w}, {2 * w}], cy in [{-h}, {2 * h}])")
    if cam.dist is not None and np.max(np.abs(cam.dist)) > MAX_DISTORTION:
        raise InputError(f"{where}distortion coefficients must be within +-{MAX_DISTORTION:g}, got "
                         f"{[float(x) for x in cam.dist]}")
    c = cam.T_world_cam[:3, 3]
    if np.max(np.abs(c)) > MAX_POSITION:
        raise InputError(f"{where}camera position {[float(x) for x in c]} is more than {MAX_POSITION:g} m from "
                         f"the origin (wrong units?)")
    return cam


def distort(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV radial/tangential distortion (k1, k2, p1, p2[, k3]) to normalised coordinates."""
    k1, k2, p1, p2 = dist[:4]
    k3 = dist[4] if dist.size > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd
