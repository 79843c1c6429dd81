"""Known/robot poses against the photos: the focal length (`hand_eye_check.intrinsics_check`) and the
image-to-pose time offset (`hand_eye_check.latency_check`, `--poses.time-offset-ms`) that best explain the
matches with the poses held fixed."""

from __future__ import annotations

import dataclasses
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.capture.camera import Camera, look_at
from splattwin.errors import InputError
from splattwin.poses import hand_eye_check as hec

F_TRUE = 300.0


# -- synthetic matches: no images, a few milliseconds ---------------------------------------------------------
def _camera(f: float, T_world_cam: np.ndarray, dc: tuple[float, float] = (0.0, 0.0)) -> Camera:
    """320x240 camera, principal point (160, 120) + dc px."""
    return Camera(K=np.array([[f, 0.0, 160.0 + dc[0]], [0.0, f, 120.0 + dc[1]], [0.0, 0.0, 1.0]]), width=320,
                  height=240, T_world_cam=T_world_cam)


def _path(t: np.ndarray) -> np.ndarray:
    """Camera poses T_world_cam [N,4,4] of a moving arm at times t (s): an arc over the scene that speeds up
    and slows down (uniform motion would leave a time offset unobservable: every relative pose the same)."""
    out = []
    for s in np.atleast_1d(t):
        a = 0.8 * s + 0.25 * np.sin(2.1 * s)                       # azimuth, rad
        eye = np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.4 + 0.05 * np.sin(1.3 * s)])
        T = look_at(eye, np.array([0.02 * np.sin(3.0 * s), 0.0, 0.0]))
        T[:3, :3] = T[:3, :3] @ Rotation.from_euler("z", 4.0 * np.sin(1.7 * s), degrees=True).as_matrix()
        out.append(T)
    return np.array(out)


def _measures(T_true: np.ndarray, f_given: float, seed: int = 0, px_noise: float = 0.25,
              dc_given: tuple[float, float] = (0.0, 0.0)):
    """Neighbour pairs (i, i+1) of cameras T_true seeing a random tabletop cloud, as `measure_pair` would give
    them: pixels projected through the true focal F_TRUE and principal point plus noise, normalised with the
    given focal and the principal point moved by dc_given px."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-0.2, 0.2, (400, 2)), rng.uniform(0.0, 0.15, 400)]
    out = []
    for i in range(len(T_true) - 1):
        uv = []
        for k in (i, i + 1):
            c = _camera(F_TRUE, T_true[k])
            Xc = (np.linalg.inv(T_true[k]) @ np.c_[X, np.ones(len(X))].T)[:3].T
            uv.append(Xc[:, :2] / Xc[:, 2:] * F_TRUE + [c.cx, c.cy] + rng.normal(0, px_noise, (len(X), 2)))
        ca, cb = _camera(f_given, T_true[i], dc_given), _camera(f_given, T_true[i + 1], dc_given)
        xa, xb = hec._rays(uv[0], ca), hec._rays(uv[1], cb)  # uv: full-size pixels, the cameras' convention
        m = hec.PairMeasure(np.eye(3), len(X), xa, xb, f_given, (320, 240), 0.3, uv[0], uv[1], ca, cb)
        out.append((i, i + 1, m))
    return out


T_VIEWS = np.linspace(0.0, 4.0, 9)  # one view every 0.5 s


@pytest.mark.parametrize("given", [1.0, 1.03, 0.97])
def test_intrinsics_check_finds_the_focal_scale(given: float):
    """A focal length given 3 % off (either way) is found (scale 1/given within 0.5 %) and warned about; the
    true one is not."""
    T = _path(T_VIEWS)
    ic = hec.intrinsics_check(_measures(T, F_TRUE * given), T, where="camera.yaml")
    assert ic is not None and ic["poses_fit"], ic
    assert abs(ic["focal_scale"] - 1.0 / given) < 0.005, ic
    assert ic["focal_scale_sigma"] < 0.005 and ic["intrinsics_file"] == "camera.yaml", ic
    if given == 1.0:
        assert ic["verdict"] == "ok" and ic["error_px_best"] <= ic["error_px_given"] + 1e-9, ic
    else:
        assert ic["verdict"] == "warn" and ic["clear_minimum"], ic
        assert ic["error_px_best"] < 0.97 * ic["error_px_given"], ic
        msg = hec.intrinsics_message(ic)
        assert "camera.yaml" in msg and f"{100 * (1 / given - 1):+.1f} %" in msg, msg


@pytest.mark.parametrize("dc", [(0.0, 0.0), (2.0, 0.0), (7.0, -6.0), (0.0, 8.0)])
def test_intrinsics_check_finds_the_principal_point(dc: tuple[float, float]):
    """A principal point given 6-8 px off (an intrinsics file with the image centre for the calibrated one)
    is found (the offset back, -dc, within 1 px) and warned about, naming the file; the true one is not, nor
    one 2 px off (below 1 % of the focal length, PP_WARN_REL). The focal length stays right: the focal scan
    alone, at the principal point as given, read 0.954 for a cx 2 px off here and warned about the focal."""
    T = _path(T_VIEWS)
    ic = hec.intrinsics_check(_measures(T, F_TRUE, dc_given=dc), T, where="camera.yaml")
    assert ic is not None, ic
    off = np.array(ic["principal_point_offset_px"])
    assert np.all(np.abs(off + np.array(dc)) < 1.0) and max(ic["principal_point_sigma_px"]) < 0.5, ic
    assert ic["verdict"] == "ok" and abs(ic["focal_scale"] - 1.0) < 0.01, ic
    assert ic["principal_point_px_best"] == pytest.approx([160.0, 120.0], abs=1.0), ic
    if max(abs(v) for v in dc) < 3.0:
        assert ic["principal_point_verdict"] == "ok", ic
    else:
        assert ic["principal_point_verdict"] == "warn" and ic["principal_point_clear_minimum"], ic
        assert ic["principal_point_error_px_best"] < 0.7 * ic["principal_point_error_px_given"], ic
        msg = hec.principal_point_message(ic)
        assert "camera.yaml" in msg and f"({off[0]:+.1f}, {off[1]:+.1f}) px" in msg and "cx/cy" in msg, msg


def test_intrinsics_check_quiet_when_the_poses_are_off():
    """Per-view pose errors (3 mm / 0.3 deg) with the true focal: the scale that fits best absorbs them, but
    the poses still do not fit at it, so no warning about the intrinsics ("undetermined")."""
    T = _path(T_VIEWS)
    rng = np.random.default_rng(3)
    T_noisy = T.copy()
    for k in range(len(T)):
        T_noisy[k, :3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.3) / np.sqrt(3), 3)).as_matrix() @ T[k, :3, :3]
        T_noisy[k, :3, 3] += rng.normal(0, 3e-3 / np.sqrt(3), 3)
    ic = hec.intrinsics_check(_measures(T, F_TRUE), T_noisy)
    assert ic is not None and ic["verdict"] != "warn" and ic["principal_point_verdict"] != "warn", ic


@pytest.mark.parametrize("delay_ms", [0.0, 40.0])
def test_latency_check_finds_the_time_offset(delay_ms: float):
    """Images stamped 40 ms after the moment they show, poses from a 100 Hz stream (interpolated as the TUM
    reader does): the offset is found (-40 ms within 10 ms) and warned about, naming the option; 0 ms is not."""
    from splattwin.capture.tum import interpolate

    T = _path(T_VIEWS)
    t_pose = np.arange(-0.5, 4.5, 0.01)
    T_pose = _path(t_pose)
    stamps = T_VIEWS + delay_ms / 1000.0

    def poses_at(dt: float):
        return interpolate(stamps + dt, t_pose, T_pose, 0.02)

    lc = hec.latency_check(_measures(T, F_TRUE), poses_at)
    assert lc is not None, lc
    assert abs(lc["time_offset_ms"] + delay_ms) < 10.0, lc
    if delay_ms:
        assert lc["verdict"] == "warn" and lc["error_px_best"] < 0.5 * lc["error_px_given"], lc
        assert f"--poses.time-offset-ms={lc['time_offset_ms']:.0f}" in hec.latency_message(lc)
    else:
        assert lc["verdict"] == "ok", lc


def test_latency_check_says_undetermined_when_no_offset_changes_the_fit():
    """A still arm (every view's pose constant in time): shifting the image times changes no relative pose,
    the error curve is flat, and the check reports "undetermined" instead of an offset read off noise."""
    T = _path(T_VIEWS)
    lc = hec.latency_check(_measures(T, F_TRUE), lambda dt: (T, np.ones(len(T), dtype=bool)))
    assert lc is not None and lc["verdict"] == "undetermined" and not lc["observable"], lc


# -- the embedded scene as a robot-style TUM capture (rendered once, ~5 s) ------------------------------------
@pytest.fixture(scope="module")
def tum_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    return write_robot_capture(tmp_path_factory.mktemp("pose_checks") / "tum",
                               SceneOptions(width=320, height=240, supersample=1),
                               RobotCaptureOptions(views=12, width=320, height=240, format="tum"), progress=False)


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("masks", "meshes"))
    return dst


def _poses(folder: Path, **kw):
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    opts = PoseOptions(method="known", progress=False, depth_points=False, triangulate=False, up="keep", **kw)
    return estimate_poses(load_dataset(folder), opts)


def test_latency_of_a_moving_arm_capture_found_and_applied(tum_capture: Path, tmp_path: Path, caplog):
    """Images stamped 40 ms late while the arm moves (one view per second, ~3 mm / 0.3 deg of pose error):
    the latency check finds -40 ms (within 10 ms), warns naming --poses.time-offset-ms; with that option
    the poses are matched at the shifted times: no warning, the matches fit, the cameras are the true ones."""
    from splattwin.capture import load_dataset
    from splattwin.scene.robot_capture import moving_arm_tum

    truth = {f.image_path.name: f.camera.T_world_cam for f in load_dataset(tum_capture).frames}
    cap = moving_arm_tum(_copy(tum_capture, tmp_path / "late"), 1.0, 100.0, 0.040)
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        res = _poses(cap)
    lc = res.stats["latency_check"]
    assert lc["verdict"] == "warn" and abs(lc["time_offset_ms"] + 40.0) < 10.0, lc
    assert f"--poses.time-offset-ms={lc['time_offset_ms']:.0f}" in caplog.text and "look offset" in caplog.text
    assert res.stats["intrinsics_check"]["verdict"] != "warn", res.stats["intrinsics_check"]

    def centre_err(r):
        return max(np.linalg.norm(f.camera.T_world_cam[:3, 3] - truth[f.image_path.name][:3, 3]) for f in r.frames)

    caplog.clear()
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        fixed = _poses(cap, time_offset_ms=lc["time_offset_ms"])
    lf = fixed.stats["latency_check"]
    assert lf["verdict"] == "ok" and lf["offset_in_use_ms"] == lc["time_offset_ms"], lf
    assert abs(lf["time_offset_ms"] - lc["time_offset_ms"]) < 5.0, lf
    assert "timestamps look offset" not in caplog.text
    assert len(fixed.frames) == len(res.frames) == len(truth)
    assert centre_err(fixed) < 0.5e-3 < 2e-3 < centre_err(res)
    assert fixed.stats["pose_consistency"]["sampson_median_px"] < 0.6 * res.stats["pose_consistency"]["sampson_median_px"]


def test_no_latency_no_focal_error_no_warning(tum_capture: Path, tmp_path: Path, caplog):
    """The same moving arm with images stamped on time, the true intrinsics: both checks quiet."""
    from splattwin.scene.robot_capture import moving_arm_tum

    cap = moving_arm_tum(_copy(tum_capture, tmp_path / "ontime"), 1.0, 100.0, 0.0)
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        res = _poses(cap)
    lc, ic = res.stats["latency_check"], res.stats["intrinsics_check"]
    assert lc["verdict"] == "ok" and abs(lc["time_offset_ms"]) < 5.0, lc
    assert ic["verdict"] == "ok" and abs(ic["focal_scale"] - 1.0) < 0.01, ic
    assert ic["principal_point_verdict"] == "ok" and np.hypot(*ic["principal_point_offset_px"]) < 1.0, ic
    assert "look off" not in caplog.text and "look offset" not in caplog.text and "looks off" not in caplog.text


def test_focal_error_in_the_intrinsics_file_warned(tum_capture: Path, tmp_path: Path, caplog):
    """camera.yaml's fx, fy 3 % too large: the check finds the scale 1/1.03 (within 1 %) and warns naming the
    file (the depth check's 5 % band and the pose consistency both miss an error this size)."""
    import yaml

    cap = _copy(tum_capture, tmp_path / "focal")
    d = yaml.safe_load((cap / "camera.yaml").read_text())
    d["fx"], d["fy"] = d["fx"] * 1.03, d["fy"] * 1.03
    (cap / "camera.yaml").write_text(yaml.safe_dump(d))
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        res = _poses(cap)
    ic = res.stats["intrinsics_check"]
    assert ic["verdict"] == "warn" and abs(ic["focal_scale"] - 1 / 1.03) < 0.01, ic
    assert ic["intrinsics_file"] == str(cap / "camera.yaml"), ic
    assert res.stats["pose_consistency"]["verdict"] == "ok"  # what the older check saw: nothing
    assert "intrinsics" in caplog.text and str(cap / "camera.yaml") in caplog.text and "look off" in caplog.text


def test_principal_point_error_in_the_intrinsics_file_warned(tum_capture: Path, tmp_path: Path, caplog):
    """camera.yaml's cx, cy 7 px right and 6 px up of the calibrated ones (what the image centre given for
    the principal point does on a camera whose centre is off): the check finds the offset back, (-7, +6) px
    within 1 px, and warns naming the file; the focal length is not blamed. The pose consistency alone
    could not tell the cause."""
    import yaml

    cap = _copy(tum_capture, tmp_path / "pp")
    d = yaml.safe_load((cap / "camera.yaml").read_text())
    d["cx"], d["cy"] = d["cx"] + 7.0, d["cy"] - 6.0
    (cap / "camera.yaml").write_text(yaml.safe_dump(d))
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        res = _poses(cap)
    ic = res.stats["intrinsics_check"]
    assert ic["principal_point_verdict"] == "warn", ic
    assert np.all(np.abs(np.array(ic["principal_point_offset_px"]) - [-7.0, 6.0]) < 1.0), ic
    assert ic["principal_point_px_given"] == pytest.approx([d["cx"] + 0.5, d["cy"] + 0.5], abs=0.01), ic
    assert ic["verdict"] == "ok" and abs(ic["focal_scale"] - 1.0) < 0.015, ic
    assert "principal point" in caplog.text and str(cap / "camera.yaml") in caplog.text
    assert "focal length scaled" not in caplog.text


def test_time_offset_needs_timestamps(tum_capture: Path):
    """--poses.time-offset-ms on poses not matched by timestamp (here the capture's poses as if matched by
    image name): a clear error naming the pose file, not silently ignored; a non-finite offset: refused."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    ds = load_dataset(tum_capture)
    by_id = dataclasses.replace(ds, meta={**{k: v for k, v in ds.meta.items() if k != "pose_track"}, "matched_by": "id"})
    with pytest.raises(InputError, match="time-offset-ms needs poses matched to the images by timestamp") as e:
        estimate_poses(by_id, PoseOptions(method="known", time_offset_ms=-40.0, progress=False))
    assert e.value.path == tum_capture / "groundtruth.txt"
    with pytest.raises(InputError, match="finite"):
        estimate_poses(ds, PoseOptions(method="known", time_offset_ms=float("nan"), progress=False))


def test_time_offset_option_on_the_command_line():
    """The option is reachable as --poses.time-offset-ms (build) and --time-offset-ms (poses)."""
    from splattwin.cli import build_parser
    from splattwin.options import from_args
    from splattwin.pipeline.cli import resolve_options
    from splattwin.poses import PoseOptions

    p = build_parser()
    assert from_args(PoseOptions, p.parse_args(["poses", "in", "out", "--time-offset-ms", "-40"])).time_offset_ms == -40.0
    o = resolve_options(p.parse_args(["build", "data", "--out", "t", "--poses.time-offset-ms=-40"]))
    assert o.poses.time_offset_ms == -40.0
    d = resolve_options(p.parse_args(["build", "data", "--out", "t"]))
    assert d.poses.time_offset_ms == 0.0


def test_robot_poses_with_a_wrong_focal_warned(scene_default: Path, tmp_path: Path, caplog):
    """Robot poses + hand-eye (exact) with the dataset's focal length 3 % too long: the robot path runs the
    intrinsics check on the pose-consistency matches, finds 1/1.03 and warns naming the dataset's file; the
    hand-eye checks stay as they were (consistent, poses ok)."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from tests.poses.test_robot import _flange_poses, _hand_eye, _write

    gt = load_dataset(scene_default)
    X = _hand_eye()
    poses = _write(tmp_path / "poses.json", gt, _flange_poses(gt, X), X)

    def longer(c: Camera) -> Camera:
        K = c.K.copy()
        K[0, 0] *= 1.03
        K[1, 1] *= 1.03
        return dataclasses.replace(c, K=K)

    ds = dataclasses.replace(gt, frames=[dataclasses.replace(f, camera=longer(f.camera)) for f in gt.frames])
    with caplog.at_level("WARNING", logger="splattwin.poses"):
        res = estimate_poses(ds, PoseOptions(method="robot", robot_poses=poses, progress=False, depth_points=False,
                                             triangulate=False))
    ic = res.stats["intrinsics_check"]
    assert ic["verdict"] == "warn" and abs(ic["focal_scale"] - 1 / 1.03) < 0.01, ic
    assert ic["intrinsics_file"] == gt.meta["path"] and gt.meta["path"] in caplog.text, ic
    assert res.stats["hand_eye_check"]["verdict"] == "consistent"
    assert "latency_check" not in res.stats  # robot pose files carry no timestamps


def test_pose_list_in_another_convention_is_refused_naming_it(tum_capture: Path, tmp_path: Path):
    """groundtruth.txt written `id tx ty tz qw qx qy qz` (EuRoC's and many ROS scripts' order), or holding
    world-to-camera poses (COLMAP's and many SLAM exports' convention), read as TUM's camera-to-world `qx qy qz
    qw`: every camera moved, warnings blaming the hand-eye, timestamps or intrinsics, and then (here with --up
    keep) a twin on wrong poses, or an up-check error blaming the table plane. Now the run stops naming the pose
    list and the convention whose poses fit the photos."""
    from splattwin.capture.tum import read_pose_list, write_pose_list
    from splattwin.transforms import invert_pose

    cap = _copy(tum_capture, tmp_path / "wxyz")
    gt = cap / "groundtruth.txt"
    lines = []
    for ln in gt.read_text().splitlines():
        f = ln.split()
        lines.append(ln if ln.startswith("#") else " ".join(f[:4] + [f[7]] + f[4:7]))
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"w x y z order: .* read as `qw qx qy qz` by 0\.\d+ px") as e:
        _poses(cap)
    assert e.value.path == gt

    cap = _copy(tum_capture, tmp_path / "w2c")
    gt = cap / "groundtruth.txt"
    write_pose_list(gt, [(k, invert_pose(T)) for k, T in read_pose_list(gt)])
    with pytest.raises(InputError, match=r"world-to-camera \(T_cam_world\): .* inverted by 0\.\d+ px") as e:
        _poses(cap)
    assert e.value.path == gt


@pytest.mark.parametrize("written", ["opencv", "inverse", "both"])
def test_transforms_json_in_another_convention_is_refused_naming_it(scene_default: Path, tmp_path: Path, written):
    """A hand-written transforms.json with OpenCV camera axes (what robot code computes) and/or world-to-camera
    poses where nerfstudio's transform_matrix is camera-to-world in OpenGL axes: it was read without a word (the
    up check turned the flipped world 'z up', 13 points triangulated instead of 240) into a twin on wrong poses.
    Now the run stops naming the file and the convention whose poses fit the photos; as written: unchanged."""
    import json

    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    cap = Path(shutil.copytree(scene_default, tmp_path / written))
    tf = cap / "transforms.json"
    meta = json.loads(tf.read_text())
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    for f in meta["frames"]:
        T_gl = np.array(f["transform_matrix"])
        T = {"opencv": T_gl @ flip, "inverse": np.linalg.inv(T_gl), "both": np.linalg.inv(T_gl @ flip)}[written]
        f["transform_matrix"] = T.tolist()
    tf.write_text(json.dumps(meta))
    opts = PoseOptions(method="known", progress=False, depth_points=False, triangulate=False)
    what = {"opencv": "OpenCV camera axes", "inverse": "world-to-camera (the inverse",
            "both": "world-to-camera in OpenCV camera axes"}[written]
    with pytest.raises(InputError, match=rf"look like {re.escape(what)}.* by 0\.\d+ px; write camera-to-world") as e:
        estimate_poses(load_dataset(cap), opts)
    assert e.value.path == tf
    res = estimate_poses(load_dataset(scene_default), opts)   # the file as nerfstudio writes it: read as before
    assert len(res.frames) == len(load_dataset(scene_default).frames)


def test_bop_scene_with_camera_to_world_poses_is_refused(tmp_path: Path):
    """scene_camera.json with each camera's pose in the world written into cam_R_w2c / cam_t_w2c: it went on
    with warnings (intrinsics undetermined, world tilted 17 deg, depth disagreeing) into a twin on wrong poses.
    Now the run stops naming scene_camera.json and the inverse that fits the photos."""
    import json

    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    cap = write_robot_capture(tmp_path / "bop", SceneOptions(width=160, height=120, supersample=1),
                              RobotCaptureOptions(views=12, width=160, height=120, format="bop"), progress=False)
    opts = PoseOptions(method="known", progress=False, depth_points=False, triangulate=False, up="keep")
    assert estimate_poses(load_dataset(cap), opts).stats["pose_consistency"]["verdict"] == "ok"   # as written
    sc = cap / "scene_camera.json"
    d = json.loads(sc.read_text())
    for v in d.values():
        R, t = np.array(v["cam_R_w2c"]).reshape(3, 3), np.array(v["cam_t_w2c"])
        v["cam_R_w2c"], v["cam_t_w2c"] = R.T.ravel().tolist(), (-R.T @ t).tolist()
    sc.write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"look like camera-to-world poses: .* inverted by 0\.\d+ px") as e:
        estimate_poses(load_dataset(cap), opts)
    assert e.value.path == sc
