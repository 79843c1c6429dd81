"""The embedded scene written as a robot-style RGB-D capture: the formats and conventions a robot
user's data comes in, so that path is tested end to end.

`write_robot_capture(out_dir, SceneOptions, RobotCaptureOptions)` renders the seeded tabletop from an
eye-in-hand-like sweep (from the robot's side of the table, looking down 50-70 degrees, the wrist camera
rolled a little from view to view) with a RealSense-D435-like colour camera (640x480, fx = fy = 615 px,
principal point slightly off centre; scaled with the image size), and writes it in a robot world that is
NOT the twin's: by default z down (the scene's world rotated 180 degrees about x, `R_capture_world`).

The depth maps are what a D435 would read, not the ray-cast truth: axial noise growing with z^2, edge
fattening, lost readings (0 in the PNG) in occlusion shadows, at depth edges and in random blobs
(`RobotCaptureOptions.depth_noise`, `splattwin.scene.depth_noise`; `DepthNoise.perfect()` writes the
ray-cast depth). Beyond a D435's 10 m range (`MAX_RANGE_M`) the depth is 0 too, perfect or not, never
clipped to 65535. The truth stays recoverable: scene.json and meshes/ (below).

Layouts (`RobotCaptureOptions.format`, in `splattwin.scene.options`):
- "bop": a BOP scene (`splattwin.capture.bop`): `scene_camera.json` (cam_K, depth_scale 1.0, world-to-
  camera poses in mm), `scene_gt.json` (obj_id = the object's scene label, model = the object's frame),
  `rgb/000000.png`, `depth/000000.png` (16-bit, mm, 0 = no reading), `mask_visib/000000_000000.png` per instance (visible
  part, from the ground-truth labels), `object_names.json` (obj_id -> the scene's object names).
- "tum": `rgb/<t>.png`, `depth/<t>.png` (16-bit, mm), `rgb.txt`, `depth.txt` (timestamps), a pose list
  `groundtruth.txt` (`t tx ty tz qx qy qz qw`, sampled 5 ms after each image so matching by nearest
  timestamp is exercised), `camera.yaml` (fx fy cx cy width height, depth_factor 1000 units per metre),
  and per-instance masks `masks/<t>_<obj_id>.png` with `masks/instances.json`.

Both also hold the scene's ground truth in its own z-up world (`scene.json` with a `robot_capture`
entry giving `R_capture_world`, and `meshes/`), so a twin built from the capture can be checked against it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera, look_at
from splattwin.errors import InputError
from splattwin.io import write_image, write_json, write_text
from splattwin.scene.depth_noise import sensor_depth, view_rng
from splattwin.scene.options import FORMATS, WORLDS, DepthNoise, RobotCaptureOptions, SceneOptions

log = logging.getLogger(__name__)

D435_SIZE = (640, 480)
D435_K = (615.0, 615.0, 321.5, 243.5)   # fx fy cx cy at 640x480 (a typical D435 colour stream)
__all__ = ["FORMATS", "MAX_RANGE_M", "WORLDS", "DepthNoise", "RobotCaptureOptions", "R_capture_world", "d435_camera", "depth_mm", "moving_arm_tum", "sweep_cameras",
           "write_robot_capture"]


def R_capture_world(world: str) -> np.ndarray:
    """[4,4] rigid transform from the scene's z-up world to the capture's world."""
    T = np.eye(4)
    if world == "z-down":
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])   # 180 degrees about x
    return T


def d435_camera(width: int, height: int, T_world_cam: np.ndarray, name: str) -> Camera:
    """D435-like colour camera scaled to width x height."""
    sx, sy = width / D435_SIZE[0], height / D435_SIZE[1]
    fx, fy, cx, cy = D435_K
    K = np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])
    return Camera(K=K, width=width, height=height, T_world_cam=T_world_cam, name=name)


def sweep_cameras(opts: RobotCaptureOptions, target: np.ndarray, seed: int) -> list[Camera]:
    """Eye-in-hand-like sweep over the table from the robot's side (-x), in the scene's z-up world."""
    rng = np.random.default_rng([seed, 16])
    cams = []
    for i in range(opts.views):
        s = (i + 0.5) / opts.views
        az = math.pi + math.radians(100.0) * (2 * s - 1) + rng.normal(0, math.radians(3.0))
        el = math.radians(opts.elevation[0] + (opts.elevation[1] - opts.elevation[0]) * (0.5 + 0.5 * math.sin(5 * s)))
        r = opts.distance[0] + (opts.distance[1] - opts.distance[0]) * (0.5 + 0.5 * math.cos(3 * s))
        eye = target + r * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        T = look_at(eye, target + rng.normal(0, 0.01, 3))
        roll = math.radians(opts.roll_deg) * rng.uniform(-1, 1)
        c, sn = math.cos(roll), math.sin(roll)
        T[:3, :3] = T[:3, :3] @ np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])  # about the optical axis
        cams.append(d435_camera(opts.width, opts.height, T, f"{i:06d}"))
    return cams


MAX_RANGE_M = 10.0  # a D435's rated maximum range; it reports nothing (0) beyond, as it does for no return


def depth_mm(depth_m: np.ndarray, max_range: float = MAX_RANGE_M) -> np.ndarray:
    """z-depth in metres (inf = no return) -> uint16 millimetres (0 = no measurement).

    Depths beyond `max_range` (at most 65.535 m, the 16-bit limit) are written as 0, not clipped: a
    clipped 65535 reads as a valid 65.5 m measurement."""
    max_mm = min(float(max_range) * 1000.0, 65535.0)
    d = np.where(np.isfinite(depth_m), np.round(depth_m * 1000.0), 0.0)
    return np.where((d > 0) & (d <= max_mm), d, 0.0).astype(np.uint16)


def write_robot_capture(out_dir: str | Path, options: SceneOptions | None = None,
                        capture: RobotCaptureOptions | None = None, progress: bool = True) -> Path:
    """Render and write the robot-style capture into `out_dir` (see module docstring). Returns out_dir."""
    from splattwin.progress import Progress

    from splattwin.capture import bop, tum
    from splattwin.scene.generator import to_u8, write_mesh_ply, build_scene, look_target, scene_record

    options = options or SceneOptions()
    capture = capture or RobotCaptureOptions(width=options.width, height=options.height)
    options.validate()
    capture.validate()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a directory", out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scene.json").unlink(missing_ok=True)  # written last: marks a complete capture

    objects, layout, marker, renderer = build_scene(options)
    cams_world = sweep_cameras(capture, look_target(objects), options.seed)
    T_cw = R_capture_world(capture.world)
    cams = [Camera(K=c.K, width=c.width, height=c.height, T_world_cam=T_cw @ c.T_world_cam, name=c.name)
            for c in cams_world]
    for surf in renderer.surfaces:
        write_mesh_ply(out / "meshes" / f"{surf.name}.ply", surf.mesh_world)

    times = [1.0 + i / 30.0 for i in range(len(cams))]          # a 30 Hz stream
    stems = [bop.image_name(i, "") if capture.format == "bop" else f"{t:.6f}" for i, t in enumerate(times)]
    gt_lists = []
    with Progress(len(cams), "rendering robot capture", unit="view", enabled=progress) as bar:
        for i, (cw, stem) in enumerate(zip(cams_world, stems)):
            view = renderer.render(cw, options.supersample)
            write_image(out / "rgb" / f"{stem}.png", to_u8(view["rgb"]))
            sensed = sensor_depth(view["depth"], float(cw.K[0, 0]), capture.depth_noise, view_rng(options.seed, i))
            write_image(out / "depth" / f"{stem}.png", depth_mm(sensed))
            insts = []
            for k, o in enumerate(objects):
                m = (view["labels"] == o.label).astype(np.uint8) * 255
                if capture.format == "bop":
                    write_image(out / "mask_visib" / bop.mask_name(i, k), m)
                elif m.any():
                    write_image(out / "masks" / f"{stem}_{o.label}.png", m)
                insts.append((o.label, cw.T_cam_world @ o.T_world_obj))
            gt_lists.append(insts)
            bar.update(1)

    names = {str(o.label): o.name for o in objects}
    if capture.format == "bop":
        bop.write_scene_gt(out / bop.SCENE_GT, gt_lists)
        write_json(out / bop.NAMES_FILE, names)
        bop.write_scene_camera(out / bop.SCENE_CAMERA, cams, depth_scale=1.0)
    else:
        write_json(out / "masks" / "instances.json", names)
        write_text(out / "rgb.txt", "# timestamp filename\n" + "".join(f"{s} rgb/{s}.png\n" for s in stems))
        write_text(out / "depth.txt", "# timestamp filename\n" + "".join(f"{s} depth/{s}.png\n" for s in stems))
        tum.write_intrinsics(out / "camera.yaml", cams[0], depth_factor=1000.0)
        tum.write_pose_list(out / "groundtruth.txt", [(f"{t + 0.005:.6f}", c.T_world_cam) for t, c in zip(times, cams)],
                            header="T_world_cam of the colour camera (OpenCV optical frame), world z down")
    scene = scene_record(options, objects, layout, marker, stems)
    scene["robot_capture"] = {**asdict(capture), "R_capture_world": T_cw.tolist(),
                              "note": "scene.json and meshes/ are in the scene's z-up world; the capture's poses "
                                      "are in R_capture_world @ that world"}
    write_json(out / "scene.json", scene)
    return out


def moving_arm_tum(folder: str | Path, view_period_s: float = 0.5, pose_rate_hz: float = 100.0,
                   image_delay_s: float = 0.0) -> Path:
    """Make a TUM capture written by `write_robot_capture` one taken while the arm moves: the camera follows a
    smooth path through the views (positions: cubic spline, rotations: `RotationSpline`, one view every
    `view_period_s` seconds), the pose list `groundtruth.txt` samples it at `pose_rate_hz`, and each image
    (and its depth image) is stamped `image_delay_s` after the moment it shows (camera latency: the right
    pose of an image stamped t is the one at t - image_delay_s). Rewrites groundtruth.txt, rgb.txt and
    depth.txt in place; returns the folder."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, RotationSpline

    from splattwin.capture import tum

    folder = Path(folder)
    images = tum._file_list(folder / "rgb.txt", folder, "image list")
    depths = tum._file_list(folder / "depth.txt", folder, "depth list")
    poses = dict(tum.read_pose_list(folder / "groundtruth.txt"))
    # the writer samples each view's pose 5 ms after its image: view k is the pose list's k-th line
    T = np.array(list(poses.values()))
    # a clock far from the file names' (1.000000.png, ...): pose ids must not match image names by id
    t_view = 100.0 + view_period_s * np.arange(len(T))
    # the arm at rest one period before the first view and after the last: every image has poses around it
    t_knot = np.r_[t_view[0] - view_period_s, t_view, t_view[-1] + view_period_s]
    T_knot = np.concatenate([T[:1], T, T[-1:]])
    pos = CubicSpline(t_knot, T_knot[:, :3, 3], axis=0)
    rot = RotationSpline(t_knot, Rotation.from_matrix(T_knot[:, :3, :3]))
    t_pose = t_knot[0] + np.arange(int(np.floor((t_knot[-1] - t_knot[0]) * pose_rate_hz)) + 1) / pose_rate_hz
    Ts = np.tile(np.eye(4), (len(t_pose), 1, 1))
    Ts[:, :3, :3] = rot(t_pose).as_matrix()
    Ts[:, :3, 3] = pos(t_pose)
    tum.write_pose_list(folder / "groundtruth.txt", [(f"{t:.6f}", M) for t, M in zip(t_pose, Ts)],
                        header=f"T_world_cam along a moving arm's path ({pose_rate_hz:g} Hz); images stamped "
                               f"{1000 * image_delay_s:g} ms late")
    stamp = t_view + image_delay_s
    write_text(folder / "rgb.txt", "# timestamp filename\n" + "".join(
        f"{t:.6f} {p.relative_to(folder).as_posix()}\n" for t, (_, p) in zip(stamp, images)))
    write_text(folder / "depth.txt", "# timestamp filename\n" + "".join(
        f"{t:.6f} {p.relative_to(folder).as_posix()}\n" for t, (_, p) in zip(stamp, depths)))
    return folder
