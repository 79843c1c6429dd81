"""Cameras for playback: the capture cameras, a user camera from YAML, and an eye-in-hand camera.

All are `splattwin.capture.Camera` (OpenCV: x right, y down, z forward; twin frame, metres). A camera
whose centre is below the table top sees the table from underneath, where the capture saw nothing:
`check_camera` refuses it with an InputError (CLI exit 2).

User camera YAML (twin frame unless `frame: hand`; every key but the pose is optional):

    width: 640                 # pixels (default 640 x 480)
    height: 480
    fov_x_deg: 60              # horizontal field of view, square pixels; or fov_y_deg; or
    # K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    # pose, one of:
    eye: [0.6, -0.5, 0.45]     # camera centre (m)
    look_at: [0.0, 0.0, 0.03]  # point at the image centre (m)
    up: [0, 0, 1]              # optional, image up towards this world direction
    # T_world_cam: 4x4 camera-to-world (OpenCV convention)
    # T_world_cam_gl: 4x4 camera-to-world (OpenGL/nerfstudio convention, e.g. from the viewer)
    frame: world               # or "hand": the pose is T_hand_cam, an eye-in-hand mount on the Panda hand

The eye-in-hand default (`EyeInHand()`): a RealSense D435-like colour camera, 640x480 with square pixels
and the D435's 42.5 deg vertical field of view (55 deg horizontal at 4:3; the datasheet's 69 x 42 deg is
its 16:9 stream: use width 1280, height 720 for that), mounted on the hand 6 cm in front of the flange
axis and 3 cm above the flange, looking down the approach direction at the fingertips' midpoint 10 cm
beyond them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera, look_at, opencv_from_opengl
from splattwin.errors import InputError
from splattwin.limits import load_yaml

D435_SIZE = (640, 480)
D435_FOV_Y_DEG = 42.5
HAND_BODY = "hand"
MAX_PIXELS = 4096 * 4096
MAX_CAMERA_YAML_BYTES = 1 << 20
MAX_CAMERA_YAML_NODES = 10_000   # a camera is a few dozen numbers


def _mount_default() -> np.ndarray:
    # hand frame: z = approach (towards the fingers), y = finger closing axis, flange at the origin
    return look_at(np.array([0.06, 0.0, 0.03]), np.array([0.0, 0.0, 0.2034]), up=np.array([1.0, 0.0, 0.0]))


@dataclass
class EyeInHand:
    """A camera rigidly mounted on a robot body (default: the Panda hand).

    width/height: pixels; fov_y_deg: vertical field of view (square pixels) unless K is given;
    T_hand_cam [4,4]: camera pose in the body's frame (OpenCV convention).
    """

    width: int = D435_SIZE[0]
    height: int = D435_SIZE[1]
    fov_y_deg: float = D435_FOV_Y_DEG
    K: np.ndarray | None = None
    T_hand_cam: np.ndarray = field(default_factory=_mount_default)
    body: str = HAND_BODY
    name: str = "wrist"

    def intrinsics(self) -> np.ndarray:
        if self.K is not None:
            return np.asarray(self.K, float)
        f = 0.5 * self.height / math.tan(math.radians(self.fov_y_deg) / 2)
        return np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1.0]])

    def scaled(self, factor: float) -> "EyeInHand":
        """The same camera for an image resized by `factor` (as `Camera.scaled`): field of view kept."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        K = None
        if self.K is not None:
            K = np.array(self.K, float)
            K[0, :] *= w / self.width
            K[1, :] *= h / self.height
        return replace(self, width=w, height=h, K=K)

    def camera(self, T_world_hand: np.ndarray) -> Camera:
        """The camera in the world for the body's pose T_world_hand [4,4]."""
        return Camera(K=self.intrinsics(), width=self.width, height=self.height,
                      T_world_cam=np.asarray(T_world_hand) @ self.T_hand_cam, name=self.name)


def check_camera(camera: Camera, table_height: float = 0.0, where: str | Path | None = None) -> Camera:
    """The camera, or InputError when its centre is below the table top (it would see the underside)."""
    z = float(camera.T_world_cam[2, 3])
    if z <= table_height:
        raise InputError(f"camera {camera.name!r} is below the table (centre at z = {z:.3f} m, table top at "
                         f"{table_height:.3f} m): the capture never saw the table from underneath", where)
    return camera


def capture_cameras_path(twin_dir: str | Path) -> Path:
    """The twin's capture cameras file (twin.json `cameras`, else poses/transforms.json)."""
    from splattwin.twin.manifest import Manifest

    twin_dir = Path(twin_dir)
    man = Manifest.load(twin_dir)
    path = Path(man.cameras) if man.cameras else Path("poses/transforms.json")
    if not path.is_absolute():
        path = twin_dir / path
    if path.is_dir():
        path = path / "transforms.json"
    return path


def capture_cameras(twin_dir: str | Path) -> list[Camera]:
    """The twin's capture cameras (twin.json `cameras`, else poses/transforms.json), named by image."""
    from splattwin.capture import nerfstudio

    path = capture_cameras_path(twin_dir)
    if not path.is_file():
        raise InputError("the twin's capture cameras file is missing", path)
    ds = nerfstudio.read(path)
    from splattwin.twin.manifest import Manifest

    refined = Manifest.load(twin_dir).config.get("refined_poses")  # training with pose refinement
    if isinstance(refined, str):
        from splattwin.paths import confined

        # a path read from twin.json: inside the twin, as its other paths (`Manifest.validate`); "/x.json" or
        # "../../x.json" read a file from elsewhere whose poses replaced the capture's
        refined = confined(twin_dir, refined, Path(twin_dir) / "twin.json", "config refined_poses path")
    if isinstance(refined, Path) and refined.is_file():
        from splattwin.splat.refined_poses import apply

        ds = apply(ds, refined)
    cams = []
    for f in ds.frames:
        c = f.camera
        cams.append(replace(c, name=Path(f.image_path).stem, dist=None))
    return cams


def load_camera_yaml(path: str | Path) -> Camera | EyeInHand:
    """A user camera (world frame) or an eye-in-hand mount (`frame: hand`) from YAML (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("camera file not found", path)
    # the bounded loader: a 489-byte file of nested aliases expanded to 10^9 floats under yaml.safe_load
    d = load_yaml(path, max_bytes=MAX_CAMERA_YAML_BYTES, max_nodes=MAX_CAMERA_YAML_NODES)
    if not isinstance(d, dict):
        raise InputError("camera YAML must be a mapping (width, height, fov_x_deg / K, eye + look_at / T_world_cam)", path)
    try:
        return _camera_from_dict(d, path)
    except (TypeError, ValueError) as e:
        raise InputError(f"malformed camera: {e}", path) from e


def _matrix(v, shape: tuple[int, ...], key: str, path: Path) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(f"{key} must be a finite {'x'.join(map(str, shape))} array", path)
    return a


def _camera_from_dict(d: dict, path: Path) -> Camera | EyeInHand:
    known = {"width", "height", "fov_x_deg", "fov_y_deg", "K", "eye", "look_at", "up", "T_world_cam",
             "T_world_cam_gl", "T_hand_cam", "frame", "name", "body"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise InputError(f"unknown camera keys: {', '.join(map(str, unknown))}", path)
    frame = d.get("frame", "world")
    if frame not in ("world", "hand"):
        raise InputError(f"frame must be 'world' or 'hand', got {frame!r}", path)
    w, h = int(d.get("width", D435_SIZE[0])), int(d.get("height", D435_SIZE[1]))
    if w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise InputError(f"image size {w}x{h} out of range", path)
    if "K" in d:
        K = _matrix(d["K"], (3, 3), "K", path)
    else:
        if "fov_x_deg" in d:
            fov = float(d["fov_x_deg"])
            half = w / 2
        else:
            fov = float(d.get("fov_y_deg", D435_FOV_Y_DEG))
            half = h / 2
        if not 1.0 <= fov <= 170.0:
            raise InputError(f"field of view {fov} deg out of range (1-170)", path)
        f = half / math.tan(math.radians(fov) / 2)
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    if "T_world_cam" in d or "T_hand_cam" in d:
        T = _matrix(d.get("T_world_cam", d.get("T_hand_cam")), (4, 4), "T_world_cam", path)
    elif "T_world_cam_gl" in d:
        T = opencv_from_opengl(_matrix(d["T_world_cam_gl"], (4, 4), "T_world_cam_gl", path))
    elif "eye" in d and "look_at" in d:
        eye = _matrix(d["eye"], (3,), "eye", path)
        tgt = _matrix(d["look_at"], (3,), "look_at", path)
        if np.linalg.norm(tgt - eye) < 1e-6:
            raise InputError("eye and look_at coincide", path)
        up = _matrix(d.get("up", [0, 0, 1]), (3,), "up", path)
        T = look_at(eye, tgt, up=up)
    elif frame == "hand":
        T = _mount_default()
    else:
        raise InputError("camera pose missing: give eye + look_at, T_world_cam or T_world_cam_gl", path)
    name = str(d.get("name", path.stem))[:64]
    if frame == "hand":
        cam = EyeInHand(width=w, height=h, K=K, T_hand_cam=T, body=str(d.get("body", HAND_BODY)), name=name)
        Camera(K=K, width=w, height=h, T_world_cam=T, name=name)   # validates the rotation
        return cam
    return Camera(K=K, width=w, height=h, T_world_cam=T, name=name)


def resolve_camera(spec: str, twin_dir: str | Path, width: int | None = None) -> Camera | EyeInHand:
    """A camera from a command-line spec: a capture image name (e.g. heldout_000), 'capture:<index>',
    'wrist' (the default eye-in-hand camera) or a camera YAML file. `width` rescales the camera (field of view
    kept)."""
    if spec in ("wrist", "hand", "eye-in-hand"):
        cam: Camera | EyeInHand = EyeInHand()
    elif spec.endswith((".yaml", ".yml")) or Path(spec).is_file():
        cam = load_camera_yaml(spec)
    else:
        cams = capture_cameras(twin_dir)
        if spec.startswith("capture:"):
            try:
                i = int(spec.split(":", 1)[1])
                if i < 0:   # not Python's count from the end: capture:-1 rendered the last camera silently
                    raise IndexError(i)
                cam = cams[i]
            except (ValueError, IndexError):
                raise InputError(f"no capture camera {spec!r} (the twin has {len(cams)}: 0..{len(cams) - 1})") from None
        else:
            found = [c for c in cams if c.name == spec]
            if not found:
                names = ", ".join(c.name for c in cams[:8]) + (" ..." if len(cams) > 8 else "")
                raise InputError(f"no capture camera named {spec!r} (have: {names}); or give 'wrist', "
                                 f"'capture:<index>' or a camera YAML")
            cam = found[0]
    if width is not None and width != cam.width:   # the wrist camera too (it was ignored silently)
        cam = cam.scaled(width / cam.width)
    # a capture camera's size is read from the twin's cameras file: 12000x9000 there took 6 GB before the
    # rasterizer gave up. Rendering is bounded like a camera YAML (MAX_PIXELS); --width scales it down.
    if cam.width * cam.height > MAX_PIXELS:
        where = spec if isinstance(cam, EyeInHand) or spec.endswith((".yaml", ".yml")) or Path(spec).is_file() \
            else capture_cameras_path(twin_dir)
        raise InputError(f"camera {cam.name!r} renders {cam.width}x{cam.height} pixels, more than the "
                         f"{MAX_PIXELS / 1e6:.1f} megapixels a video frame may have; give a smaller --width", where)
    return cam
