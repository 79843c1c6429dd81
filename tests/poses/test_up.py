"""Up-axis sanity for known poses: cues, snapping to world axes, levelling tilted worlds, ambiguity, and
estimate_poses turning a z-down world z up (recorded in frame.json)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.capture import Camera, Dataset, load_dataset, look_at, nerfstudio
from splattwin.cli import main
from splattwin.errors import InputError
from splattwin.poses import PoseOptions, estimate_poses, load_frame
from splattwin.poses.up import axis_rotation, camera_cue, check_up, level_rotation


def _tabletop(n_cams: int = 10, seed: int = 0) -> tuple[list[Camera], np.ndarray]:
    """Cameras on a 200-degree arc above a table (z up), rolled a little, and points on the table + a box."""
    rng = np.random.default_rng(seed)
    cams = []
    for i, az in enumerate(np.linspace(-1.7, 1.7, n_cams) + np.pi):
        el = math.radians(rng.uniform(35, 70))
        eye = 0.6 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        T = look_at(eye, rng.normal(0, 0.02, 3))
        T[:3, :3] = T[:3, :3] @ Rotation.from_euler("z", rng.uniform(-20, 20), degrees=True).as_matrix()
        cams.append(Camera.from_fov(1.0, 64, 48, T_world_cam=T, name=f"c{i}"))
    table = np.column_stack([rng.uniform(-0.4, 0.4, (3000, 2)), rng.normal(0, 0.0005, 3000)])
    box = rng.uniform([-0.05, -0.05, 0.0], [0.05, 0.05, 0.1], (600, 3))
    return cams, np.vstack([table, box])


def _moved(R_in: np.ndarray, cams: list[Camera], pts: np.ndarray) -> tuple[list[Camera], np.ndarray]:
    T = np.eye(4)
    T[:3, :3] = R_in
    return [dataclasses.replace(c, T_world_cam=T @ c.T_world_cam) for c in cams], pts @ R_in.T


def _up_after(R_twin_input: np.ndarray, R_in: np.ndarray) -> float:
    """Degrees between the true up carried through input and correction, and +z."""
    z = (R_twin_input @ R_in)[:, 2]
    return math.degrees(math.acos(np.clip(z[2], -1, 1)))


@pytest.mark.parametrize("axis, R_in", [
    ("+z", np.eye(3)),
    ("-z", np.diag([1.0, -1.0, -1.0])),
    ("+y", Rotation.from_euler("x", -90, degrees=True).as_matrix()),
    ("-x", Rotation.from_euler("y", -90, degrees=True).as_matrix() @ Rotation.from_euler("z", 30, degrees=True).as_matrix()),
])
def test_world_axis_up_is_found_and_turned_exactly(axis, R_in):
    cams, pts = _moved(R_in, *_tabletop())
    chk = check_up(cams, pts)
    assert chk.input_up == axis and chk.source == "table_plane+cameras"
    np.testing.assert_allclose(chk.R_twin_input, axis_rotation(axis), atol=0)
    assert _up_after(chk.R_twin_input, R_in) < 1e-9          # a quarter/half turn: exact, not a fit
    assert chk.changed == (axis != "+z")
    if axis == "-z":
        np.testing.assert_array_equal(chk.R_twin_input, np.diag([1.0, -1.0, -1.0]))
        assert "180.0 degrees about +x" in chk.describe()


def test_cameras_alone_find_a_z_down_world():
    cams, _ = _moved(np.diag([1.0, -1.0, -1.0]), *_tabletop())
    chk = check_up(cams, None)
    assert chk.input_up == "-z" and chk.source == "cameras"
    assert "fewer than 50 points" in chk.evidence["table_plane"]


def test_tilted_world_is_levelled_by_the_table_plane():
    R_in = Rotation.from_rotvec(math.radians(33) * np.array([1, 1, 0]) / math.sqrt(2)).as_matrix()
    cams, pts = _moved(R_in, *_tabletop())
    chk = check_up(cams, pts)
    assert chk.input_up == "tilted" and chk.evidence["angle_to_axis_deg"] > 30
    assert _up_after(chk.R_twin_input, R_in) < 0.1        # the plane fit, not a guess
    np.testing.assert_allclose(level_rotation(chk.up_input) @ chk.up_input, [0, 0, 1], atol=1e-12)


def test_a_wall_as_dominant_plane_is_ambiguous():
    cams, _ = _tabletop()
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.full(4000, 0.8), rng.uniform(-0.4, 0.4, 4000), rng.uniform(0, 0.5, 4000)])
    with pytest.raises(InputError, match=r"cannot tell which way is up.*wall.*--up=\+z") as e:
        check_up(cams, wall, where="scan/transforms.json")
    assert str(e.value.path) == "scan/transforms.json"


def test_cameras_pointing_everywhere_without_points_are_ambiguous():
    rng = np.random.default_rng(2)
    cams = [Camera.from_fov(1.0, 64, 48, T_world_cam=np.block([[Rotation.random(random_state=k).as_matrix(),
                                                                 rng.normal(size=(3, 1))], [np.zeros((1, 3)), 1]]))
            for k in range(40)]
    assert camera_cue(cams)[1] < 0.5 and camera_cue(cams)[2] == "view"
    with pytest.raises(InputError, match="cameras disagree"):
        check_up(cams, None)


def test_given_axis_is_used_without_detection():
    cams, pts = _tabletop()  # z up, but the user says -y is up: trusted
    chk = check_up(cams, pts, up="-y")
    assert chk.source == "given" and chk.input_up == "-y"
    np.testing.assert_allclose(chk.R_twin_input @ [0, -1, 0], [0, 0, 1], atol=1e-12)


# -- estimate_poses --------------------------------------------------------------------------------
def _z_down_copy(scene: Path, out: Path) -> Path:
    """The embedded scene's dataset with every pose in a z-down world (180 degrees about x)."""
    ds = load_dataset(scene)
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [dataclasses.replace(f, camera=dataclasses.replace(f.camera, T_world_cam=F @ f.camera.T_world_cam))
              for f in ds.frames]
    from splattwin.capture.bundle import bundle_frames

    return nerfstudio.write(Dataset(root=out, frames=bundle_frames(frames, out), has_poses=True), out / "transforms.json")


def test_estimate_poses_turns_a_z_down_world_z_up(scene_small: Path, tmp_path: Path):
    gt = load_dataset(scene_small)
    zdown = load_dataset(_z_down_copy(scene_small, tmp_path))
    res = estimate_poses(zdown, PoseOptions(method="known", progress=False))
    np.testing.assert_allclose(res.T_out_in, np.diag([1.0, -1.0, -1.0, 1.0]), atol=0)
    for a, b in zip(res.frames, gt.frames):
        np.testing.assert_allclose(a.camera.T_world_cam, b.camera.T_world_cam, atol=1e-12)
    assert res.frame.up == "+z" and res.frame.up_check["input_up"] == "-z"
    assert res.frame.up_check["source"] == "table_plane+cameras"        # the plane from the depth images
    # the back-projected depth cloud lands on the z-up table: its dominant plane is z = 0 with normal +z
    from splattwin.poses.table import fit_table_plane

    plane = fit_table_plane(res.points_xyz, np.array([c.center for c in res.cameras]))
    assert math.degrees(math.acos(plane.normal[2])) < 1.0 and abs(plane.d) < 0.005
    out = tmp_path / "poses"
    res.save(out)
    frame = load_frame(out)
    np.testing.assert_allclose(frame.T_twin_input, np.diag([1.0, -1.0, -1.0, 1.0]))
    assert "rotated 180.0 degrees about +x" in frame.description
    # chained: reading our own output again changes nothing and keeps the record of the input's world
    again = estimate_poses(load_dataset(out), PoseOptions(method="known", progress=False))
    np.testing.assert_allclose(again.T_out_in, np.eye(4))
    np.testing.assert_allclose(again.frame.T_twin_input, np.diag([1.0, -1.0, -1.0, 1.0]))


def test_z_up_scene_is_left_alone_and_keep_trusts_the_poses(scene_small: Path, tmp_path: Path):
    res = estimate_poses(load_dataset(scene_small), PoseOptions(method="known", progress=False))
    np.testing.assert_array_equal(res.T_out_in, np.eye(4))
    assert res.frame.up_check["input_up"] == "+z" and res.frame.up_check["applied"] == "none"
    zdown = load_dataset(_z_down_copy(scene_small, tmp_path))
    kept = estimate_poses(zdown, PoseOptions(method="known", up="keep", progress=False))
    np.testing.assert_array_equal(kept.T_out_in, np.eye(4))   # today's behaviour, on request only
    assert kept.frame.up_check == {"input_up": "kept as given (--up keep)"}


def test_poses_cli_up_option(scene_small: Path, tmp_path: Path, capsys):
    src = _z_down_copy(scene_small, tmp_path / "in")
    assert main(["poses", str(src), str(tmp_path / "a"), "--known", "--up=-z"]) == 0
    fr = json.loads((tmp_path / "a" / "frame.json").read_text())
    assert fr["up_check"]["source"] == "given" and fr["T_twin_input"][2][2] == -1.0
    with pytest.raises(SystemExit):
        main(["poses", str(src), str(tmp_path / "b"), "--known", "--up=down"])
    with pytest.raises(InputError, match="--up"):
        estimate_poses(load_dataset(src), PoseOptions(method="known", up="z"))


def test_cameras_alone_never_level_a_tilted_world():
    R_in = Rotation.from_rotvec(math.radians(40) * np.array([1, 1, 0]) / math.sqrt(2)).as_matrix()
    cams, _ = _moved(R_in, *_tabletop())
    with pytest.raises(InputError, match="cannot be levelled reliably"):
        check_up(cams, None)
    cams, _ = _moved(Rotation.from_euler("x", 20, degrees=True).as_matrix(), *_tabletop())
    chk = check_up(cams, None)     # 20 degrees off +z with cameras only: taken as +z, not levelled
    assert chk.input_up == "+z" and not chk.changed


def test_horizon_cue_of_rolled_and_upward_looking_cameras():
    # cameras looking up at something (a statue) with level horizons: the horizon cue still finds up
    rng = np.random.default_rng(3)
    cams = [Camera.from_fov(1.0, 64, 48, T_world_cam=look_at(np.array([np.cos(a), np.sin(a), 0.0]),
                                                              np.array([0.0, 0.0, 0.6]) + rng.normal(0, 0.05, 3)))
            for a in np.linspace(0, 1.5, 9)]
    up, strength, kind = camera_cue(cams)
    assert kind == "horizon" and math.degrees(math.acos(up[2])) < 1.0


def _wall(n: int = 6000, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([np.full(n, 0.8), rng.uniform(-0.6, 0.6, n), rng.uniform(0, 0.8, n)])


def test_table_frame_of_an_sfm_capture_takes_the_table_not_a_larger_wall(caplog):
    """SfM frames have no up of their own: the dominant plane is the table unless the cameras' horizon
    says it is a wall (here twice the table's points), then the largest level plane is."""
    from splattwin.poses.table import fit_table_plane
    from splattwin.poses.up import table_plane_under_cameras

    R_in = Rotation.from_euler("xyz", [70, -20, 140], degrees=True).as_matrix()  # an arbitrary SfM frame
    cams, pts = _tabletop()
    cams, pts = _moved(R_in, cams, np.vstack([pts, _wall()]))
    up = R_in[:, 2]
    centres = np.array([c.center for c in cams])
    assert abs(fit_table_plane(pts, centres).normal @ up) < 0.05  # the dominant plane is the wall
    plane, ev = table_plane_under_cameras(pts, cams)
    assert math.degrees(math.acos(min(1.0, plane.normal @ up))) < 1.0
    assert ev["table"] == "level plane under a wall" and ev["dominant_plane_tilt_deg"] > 85
    assert abs(plane.d) < 0.01  # the table top passes through the origin of the moved frame
    assert "a wall, not a table" in caplog.text
    # a tabletop without the wall: the dominant plane, unchanged
    cams, pts = _moved(R_in, *_tabletop())
    plane, ev = table_plane_under_cameras(pts, cams)
    ref = fit_table_plane(pts, np.array([c.center for c in cams]))
    np.testing.assert_allclose(plane.normal, ref.normal)
    assert ev["table"] == "dominant plane"


def test_sfm_capture_without_a_level_plane_is_levelled_by_the_cameras(caplog):
    from splattwin.poses.up import table_plane_under_cameras

    R_in = Rotation.from_euler("xyz", [10, 80, -30], degrees=True).as_matrix()
    cams, _ = _tabletop()
    cams, pts = _moved(R_in, cams, _wall())
    plane, ev = table_plane_under_cameras(pts, cams)
    up = R_in[:, 2]
    cue = camera_cue(cams)[0]
    np.testing.assert_allclose(plane.normal, cue)
    assert math.degrees(math.acos(min(1.0, cue @ up))) < 10  # rolled +-20 deg each: the horizon still holds
    heights = pts @ plane.normal + plane.d
    assert np.mean(heights >= 0) == pytest.approx(0.98, abs=0.005)  # z = 0 at the lowest points
    assert ev["table"].startswith("none level") and "levelled by the cameras" in caplog.text


def test_a_sloped_dominant_plane_is_taken_with_a_warning(caplog):
    """Neither level (within 15 degrees of the cameras' up) nor a wall (beyond 60): the british_museum facade
    became the "table" at 38 degrees without a word. Taken as before, with a warning."""
    import logging

    from splattwin.poses.up import table_plane_under_cameras

    cams, pts = _tabletop()
    with caplog.at_level(logging.WARNING, logger="splattwin.poses.up"):
        plane, ev = table_plane_under_cameras(pts, cams)
    assert ev["table"] == "dominant plane" and "is this a tabletop capture" not in caplog.text
    sloped = pts @ Rotation.from_euler("x", 35, degrees=True).as_matrix().T
    with caplog.at_level(logging.WARNING, logger="splattwin.poses.up"):
        plane, ev = table_plane_under_cameras(sloped, cams)
    assert ev["table"] == "dominant plane" and 30 < ev["dominant_plane_tilt_deg"] < 40
    assert "is this a tabletop capture" in caplog.text


# -- scale of known poses ---------------------------------------------------------------------------------------
def _ns_process_data_copy(scene: Path, out: Path, s: float, marks: dict | None) -> Path:
    """The embedded scene's transforms.json as nerfstudio's COLMAP converter leaves it: the poses in SfM units
    (lengths x s, about the origin) and `applied_transform` (or the given `marks`); no depth (SfM has none)."""
    import shutil

    shutil.copytree(scene / "images", out / "images")
    meta = json.loads((scene / "transforms.json").read_text())
    for fr in meta["frames"]:
        fr.pop("depth_file_path", None)
        fr.pop("label_path", None)
        T = np.asarray(fr["transform_matrix"], dtype=float)
        T[:3, 3] *= s
        fr["transform_matrix"] = T.tolist()
    meta.pop("label_objects", None)
    meta.update(marks if marks is not None else {"applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]})
    (out / "transforms.json").write_text(json.dumps(meta))
    return out / "transforms.json"


def _mean_height(res) -> float:
    return float(np.mean([c.center[2] for c in res.cameras]))


@pytest.mark.parametrize("marks", [None, {"frames_mark": "colmap_im_id"}])
def test_poses_from_nerfstudio_colmap_converter_are_unscaled(scene_small: Path, tmp_path: Path, marks, caplog):
    """ns-process-data output is SfM output: the table frame in its own units, marked unscaled (it was taken as
    metres: a twin 1/s too large, every metre threshold wrong); --scale metric overrides."""
    gt = estimate_poses(load_dataset(scene_small), PoseOptions(method="known", progress=False))
    s = 0.37
    src = _ns_process_data_copy(scene_small, tmp_path / "ns", s, None if marks is None else {})
    if marks is not None:  # the per-frame mark of nerfstudio's colmap_to_json instead of applied_transform
        meta = json.loads(src.read_text())
        for i, fr in enumerate(meta["frames"]):
            fr["colmap_im_id"] = i + 1
        src.write_text(json.dumps(meta))
    ds = load_dataset(src)
    res = estimate_poses(ds, PoseOptions(method="known", progress=False))
    assert not res.frame.scaled and res.frame.source == "unscaled"
    assert "not metres" in caplog.text
    # the table frame: table top at z = 0, cameras above it at s times their metric height
    assert _mean_height(res) == pytest.approx(s * _mean_height(gt), rel=0.03)
    metric = estimate_poses(load_dataset(src), PoseOptions(method="known", scale="metric", progress=False))
    assert metric.frame.scaled and metric.frame.source == "known_poses"


def test_scale_option_marks_other_known_poses_unscaled(scene_small: Path, tmp_path: Path):
    src = _ns_process_data_copy(scene_small, tmp_path / "ns", 1.0, {})   # no SfM marks: taken as metric
    assert estimate_poses(load_dataset(src), PoseOptions(method="known", progress=False)).frame.scaled
    assert main(["poses", str(src), str(tmp_path / "p"), "--known", "--scale", "unscaled"]) == 0
    fr = json.loads((tmp_path / "p" / "frame.json").read_text())
    assert fr["scaled"] is False and fr["source"] == "unscaled"


def test_3dgs_cameras_json_and_colmap_are_unscaled_unless_told():
    from splattwin.poses.estimate import _input_scaled

    def ds(fmt):
        return Dataset(root=Path("."), frames=[], has_poses=True, meta={"format": fmt, "path": "x"})

    assert not _input_scaled(ds("cameras.json"), None, "auto")
    assert not _input_scaled(ds("colmap"), None, "auto")
    assert _input_scaled(ds("cameras.json"), None, "metric")
    assert _input_scaled(ds("nerfstudio"), None, "auto")
    assert not _input_scaled(ds("nerfstudio"), None, "unscaled")


def test_a_tilted_known_world_gets_the_table_frame(scene_small: Path, tmp_path: Path):
    """Poses in the first camera's frame (a tilted world, arbitrary origin): levelled AND moved so that the
    table top is z = 0 near the origin; before, only levelled, its table top stayed 0.7 m below z = 0."""
    ds = load_dataset(scene_small)
    T_in_world = np.linalg.inv(ds.frames[0].camera.T_world_cam)     # input = camera 0's frame
    frames = [dataclasses.replace(f, camera=dataclasses.replace(f.camera, T_world_cam=T_in_world @ f.camera.T_world_cam))
              for f in ds.frames]
    from splattwin.capture.bundle import bundle_frames

    out = tmp_path / "cam0"
    src = nerfstudio.write(Dataset(root=out, frames=bundle_frames(frames, out), has_poses=True), out / "transforms.json")
    res = estimate_poses(load_dataset(src), PoseOptions(method="known", progress=False))
    assert res.frame.up_check["input_up"] == "tilted" and res.frame.up_check["moved_to_table_frame"]
    assert res.frame.scaled and "table frame" in res.frame.description
    from splattwin.poses.table import fit_table_plane

    plane = fit_table_plane(res.points_xyz, np.array([c.center for c in res.cameras]))
    assert math.degrees(math.acos(plane.normal[2])) < 1.0 and abs(plane.d) < 0.005
    # a rigid move of the true world: camera heights above the table and distances are the true ones
    gt = [f.camera.center for f in ds.frames]
    got = [c.center for c in res.cameras]
    np.testing.assert_allclose([p[2] for p in got], [p[2] for p in gt], atol=0.005)
    # the origin near the table centre (the true world's origin): the cameras' mean as far from it as in truth
    assert np.linalg.norm(np.mean(got, 0)[:2]) == pytest.approx(np.linalg.norm(np.mean(gt, 0)[:2]), abs=0.03)
