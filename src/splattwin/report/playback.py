"""The report's "task in motion" section: the MP4 of the validated task rendered photoreal from one
camera (moving splats, the robot as Gaussians; `splattwin.playback`; the physics frames are the robot
section's), and a picture of the final state with the hole-filled table regions outlined, with their area
and the fraction of the picture they cover; for a re-lit twin, the light it estimated and a picture to check it
(the table it puts in the objects' shadows, outlined at the start).

The video is cached in TWIN/report/ (task_<camera>.mp4 + its key: the rollout's content and the
settings), so re-writing the report does not re-render an unchanged task.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.report.options import ReportOptions

OUTLINE_RGB = (1.0, 0.0, 1.0)
SHADOW_RGB = (0.0, 0.9, 1.0)


def choose_camera(twin: Path, spec: str, width: int):
    """The video's camera: `spec` as `playback.cameras.resolve_camera`, 'auto' = first held-out capture
    camera, else the first capture camera; rescaled to `width` (the wrist camera too)."""
    from splattwin.playback.cameras import capture_cameras, resolve_camera

    if spec == "auto":
        cams = capture_cameras(twin)
        held = [c.name for c in cams if c.name.startswith("heldout")]
        spec = held[0] if held else "capture:0"
    return spec, resolve_camera(spec, twin, width=width)


def fill_outline(mask: np.ndarray) -> np.ndarray:
    """[H,W] bool: the 1-pixel inner boundary of a bool mask (4-neighbourhood)."""
    from scipy import ndimage

    return mask & ~ndimage.binary_erosion(mask, structure=np.ones((3, 3), bool), border_value=0)


def filled_picture(renderer, camera, poses: dict) -> tuple[np.ndarray, float, np.ndarray]:
    """(rgb [H,W,3] with the filled regions outlined in magenta, fraction of the picture's pixels that show
    fill, the fill mask [H,W] bool) for the state `poses` (robot not drawn)."""
    rgb = renderer.render(camera, poses, None).rgb.copy()
    mask = renderer.fill_mask(camera, poses) > 0.5
    edge = fill_outline(mask)
    from scipy import ndimage

    edge = ndimage.binary_dilation(edge) if min(mask.shape) >= 200 else edge   # visible at report size
    rgb[mask] = 0.8 * rgb[mask] + 0.2 * np.asarray(OUTLINE_RGB)
    rgb[edge] = OUTLINE_RGB
    return rgb, float(mask.mean()), mask


def light_check_picture(renderer, camera) -> tuple[np.ndarray, float] | None:
    """The start state with the table splats the estimated light puts in the objects' shadows outlined in
    cyan (they should trace the dark shadows in the photo: a wrong light shows at a glance), and the share
    of the picture they cover; None when the twin is not re-lit."""
    from splattwin.splat.rendering import render

    rl = renderer.relighter
    if rl is None:
        return None
    sc = renderer.scene
    rgb = renderer.render(camera, {}, None).rgb.copy()
    g = sc.gaussians({})   # [backdrop | background | objects] at the twin poses
    nb = len(sc.backdrop) if sc.backdrop is not None else 0
    feat = np.zeros((len(g), 1))
    feat[nb:nb + len(sc.background), 0] = (rl.static_on_table & (rl.static_lit0 < 0.5)).astype(float)
    img, _ = render(g, camera, colors=feat, backend=renderer.backend)
    mask = img[..., 0] > 0.5
    edge = fill_outline(mask)
    rgb[edge] = SHADOW_RGB
    return rgb, float(mask.mean())


def _base(twin: Path) -> np.ndarray:
    from splattwin.robot.world import BasePose

    return BasePose.recorded(twin / "robot" / "results.json").matrix()


def task_video(twin: Path, options: ReportOptions, progress: bool = False) -> dict | None:
    """Render (or reuse) the task video and the filled-regions picture. None when the twin has no rollout;
    InputError when it has no splats."""
    from splattwin.errors import InputError
    from splattwin.paths import is_inside
    from splattwin.playback.cameras import EyeInHand
    from splattwin.playback.compositor import PlaybackRenderer, rollout_state
    from splattwin.playback.movie import render_rollout_video
    from splattwin.playback.robot import RobotSplats
    from splattwin.playback.scene import DynamicScene
    from splattwin.robot.rollout import Rollout

    rpath = twin / "robot" / "rollout.npz"
    if not rpath.is_file():
        return None
    scene = DynamicScene.load(twin)
    spec, camera = choose_camera(twin, options.video_camera, options.video_width)
    rollout = Rollout.load(rpath)
    T_base = _base(twin)
    renderer = PlaybackRenderer(scene, RobotSplats.panda(T_base))
    key = {"rollout_sha256": hashlib.sha256(rpath.read_bytes()).hexdigest(), "options": asdict(options),
           "camera": spec, "base": T_base.round(9).tolist(),
           "light": scene.light.to_dict() if scene.light is not None else None,
           "twin_json_sha256": hashlib.sha256((twin / "twin.json").read_bytes()).hexdigest()}
    safe = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in spec)[:64]
    mp4 = twin / "report" / f"task_{safe}.mp4"
    keyfile = mp4.with_suffix(".json")
    for p in (mp4, keyfile):   # a received twin's folder there failed the video's final rename: an internal error
        if p.is_dir() and not p.is_symlink():
            raise InputError("a folder stands where the report writes its task video (or its key): remove it", p)
    # the cached video is embedded as it is: one that leads out of the twin (a received twin's link with a
    # matching key, which the twin's own files give) would put any file of this machine into the report; its
    # key file is read like any record of a received twin (bounded), and its numbers must be numbers
    cached = io.read_record(keyfile) if (keyfile.is_file() and mp4.is_file() and is_inside(mp4, twin)
                                         and is_inside(keyfile, twin)) else None
    info = cached.get("info") if isinstance(cached, dict) and cached.get("key") == json.loads(json.dumps(key)) else None
    if not _video_info_ok(info):
        info = render_rollout_video(renderer, rollout, camera, mp4, fps=options.video_fps, progress=progress)
        io.write_json(keyfile, {"key": key, "info": info})
    final, _ = rollout_state(rollout, len(rollout) - 1)
    pic_cam = camera if not isinstance(camera, EyeInHand) else choose_camera(twin, "auto", options.video_width)[1]
    picture, fraction, _ = filled_picture(renderer, pic_cam, final)
    check = light_check_picture(renderer, pic_cam)
    moved = scene.moved(final)
    areas = {n: scene.fills[n].to_dict()["area_m2"] for n in moved if n in scene.fills}
    return {"mp4": mp4, "info": info, "camera": spec, "picture": picture, "fill_fraction": fraction,
            "fill_area_m2": areas, "moved": moved, "light": scene.light,
            "light_check": check[0] if check is not None else None}


def _video_info_ok(info) -> bool:
    """A cached video's record as `render_rollout_video` writes it: positive frame counts, sizes and rate."""
    if not isinstance(info, dict):
        return False
    nums = [info.get(k) for k in ("frames", "width", "height", "fps")]
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < 1e7 for v in nums)


def playback_section(sec, twin: Path, options: ReportOptions | None = None) -> None:
    """Fill the report section (see the module docstring); a one-line note when there is nothing to show."""
    from splattwin.errors import InputError

    options = options or ReportOptions()
    if not options.video:
        sec.text("task video disabled (--no-video)")
        return
    try:
        v = task_video(twin, options)
    except InputError as e:
        sec.text(f"no photoreal playback: {e}")
        return
    if v is None:
        sec.text("no executed task to play (splattwin plan TWIN writes robot/rollout.npz)")
        return
    i = v["info"]
    sec.text(f"The validated task rendered photoreal from camera {v['camera']} ({i['width']}×{i['height']}, "
             f"{i['frames']} frames at {i['fps']:g} fps): the objects' Gaussians move with the simulation, the "
             f"Panda is drawn as Gaussians sampled from its meshes, the table under picked objects is filled.")
    light = v.get("light")
    if light is not None:
        sec.text(f"Re-lit: moved objects cast and receive shadows under the light estimated from the twin's own "
                 f"shadows (azimuth {light.azimuth_deg:.0f}°, elevation {light.elevation_deg:.0f}° in the twin frame, "
                 f"ambient share {light.ambient:.2f}; the table in the objects' shadows is {light.shadow_ratio:.2f} "
                 f"as bright as around them, {light.shadowed} of {light.receivers} table splats).")
        if v.get("light_check") is not None:
            sec.image(v["light_check"], caption="the light check: at the start, the table the estimated light puts "
                                                "in the objects' shadows, outlined in cyan (it should trace the "
                                                "shadows in the picture)", width=max(320, i["width"]), photo=True)
    else:
        sec.text("Not re-lit: no clear cast shadow of the objects on the table was found (soft or many lights, or "
                 "too few table splats around the objects), so every splat keeps the colour it was trained with; "
                 "a moved object's old shadow stays on the table.")
    from splattwin.report.build import physics_overview

    # the MuJoCo frames of the same task are in the robot section above: embedded here as well, the report
    # carried the same picture twice
    physics = ("the same task in MuJoCo physics: the robot section above" if physics_overview(twin) is not None
               else "no physics frames: the run had no offscreen GL context or --no-render")
    sec.video(v["mp4"], caption=f"photoreal twin in motion ({v['camera']}); {physics}", width=max(320, i["width"]))
    sec.image(v["picture"], caption=f"final state; hole-filled table regions outlined in magenta "
                                    f"({100 * v['fill_fraction']:.1f} % of this picture)", width=max(320, i["width"]),
              photo=True)
    if v["fill_area_m2"]:
        sec.table(["moved object", "filled area (cm²)"],
                  [[n, round(a * 1e4, 1)] for n, a in v["fill_area_m2"].items()])
    sec.kpis({"filled fraction of the picture": f"{100 * v['fill_fraction']:.1f} %"})
