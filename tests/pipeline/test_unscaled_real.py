"""Real photos without metric scale (the cake: 8 phone-video frames, 683x384, read in place, CC BY-NC):

- with no scale the twin is still complete (geometry, every export, report, viewer data), marked
  unscaled everywhere, and only `plan` refuses it (exit 2, saying how to give scale);
- `--known-length` turns the same SfM frame metric (the cameras' mean height is the length given);
- the marker path on the same photos: an ArUco marker composited into each photo where a marker lying on
  the table plane would appear (through each photo's SfM camera) gives the marker frame and its scale.

One SfM run (~1 min; the session fixture `cake_sfm` of tests/conftest.py, shared with
tests/poses/test_sfm_real.py) serves every test: the later pose runs re-use its finished model (in a copy).
Training is short (400 steps at half resolution): these tests check completeness and frames, not fidelity.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def _bench_real(real: Path):
    """bench/real.py (the cake's colour masks and the completeness checks live there, shared with the bench)."""
    spec = importlib.util.spec_from_file_location("bench_real", ROOT / "bench" / "real.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.DATA = real
    return mod


@pytest.fixture(scope="module")
def sfm(cake_sfm, tmp_path_factory):
    """(work dir with the finished SfM model, the unscaled PoseResult, its saved poses folder): the session's
    cake SfM run (conftest.py `cake_sfm`), its work dir and poses folder copied, since the later pose runs
    here resume in the work dir."""
    work, res, poses = cake_sfm
    tmp = tmp_path_factory.mktemp("cake")
    shutil.copytree(work, tmp / "sfm")
    shutil.copytree(poses, tmp / "poses")
    return tmp / "sfm", res, tmp / "poses"


def test_unscaled_frame_from_sfm(sfm):
    _, res, poses = sfm
    frame = json.loads((poses / "frame.json").read_text())
    assert frame["source"] == "unscaled" and frame["scaled"] is False and frame["units"] == "unscaled"
    # the nominal metre: the cameras' median view depth over 0.7 m, in SfM units
    from splattwin.poses.table import nominal_metre

    assert frame["nominal_metre"] == pytest.approx(nominal_metre(res.cameras, res.points_xyz), rel=1e-4)
    depth = np.median([np.linalg.norm(c.center) for c in res.cameras])  # cameras' distance to the table centre
    assert 0.3 * depth < 0.7 * frame["nominal_metre"] < 1.5 * depth


def test_unscaled_build_is_complete_and_plan_refuses(sfm, real_data, tmp_path, capsys):
    from splattwin.cli import main

    _, _, poses = sfm
    bench = _bench_real(real_data)
    masks = bench.cake_masks(tmp_path / "masks")
    twin = tmp_path / "twin"
    # 400 steps at half size: the dense training defaults (the sparse profile's higher densification
    # threshold grows too few Gaussians on the cake in so short a run; bench/real.py builds the same
    # capture with the defaults, 1000 steps). At 120 steps the cake's mesh collapsed to a sliver for
    # 3 of seeds 0-4 (400: 0 of 5)
    rc = main(["build", str(poses), "--masks", str(masks), "--out", str(twin), "--iters", "400",
               "--resolution", "2", "--no-progress", "--splat.sparse-views", "0"])
    assert rc == 0, capsys.readouterr().err[-2000:]
    checks = bench.unscaled_twin_checks(twin)
    assert all(checks.values()), checks
    man = json.loads((twin / "twin.json").read_text())
    nm = man["frame"]["nominal_metre"]
    assert nm > 0 and man["config"]["geometry"]["dbscan_eps"] == pytest.approx(0.02 * nm, rel=1e-4)
    fusion = json.loads((twin / "semantics" / "fusion.json").read_text())
    assert json.dumps(fusion).count(str(round(0.02 * nm, 6))[:6]) >= 1  # depth tolerance / eps in SfM units
    capsys.readouterr()
    assert main(["plan", str(twin)]) == 2
    err = capsys.readouterr().err
    assert "not metrically scaled" in err and "--known-length" in err and "--marker-size" in err


def test_known_length_makes_the_frame_metric(sfm, cake_images):
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    work, unscaled, _ = sfm
    # a baseline between two shots (measured with a tape, say): 0.30 m between frames 20 and 112.
    # (camera_height works too since SfM's registration sanity check drops the two frames the retries
    # posed at the table plane's height: see test_camera_height_makes_the_frame_metric)
    res = estimate_poses(load_dataset(cake_images),
                         PoseOptions(work_dir=work, known_length="baseline@frame000020,frame000112=0.30",
                                     progress=False))
    f = res.frame
    assert f.source == "table_plane+known_length" and f.scaled and f.units == "m" and f.nominal_metre is None
    by = {Path(fr.image_path).stem: fr.camera for fr in res.frames}
    assert np.linalg.norm(by["frame000020"].center - by["frame000112"].center) == pytest.approx(0.30, rel=1e-6)
    assert f.length_scale() == 1.0  # a metric twin's thresholds are used as written
    # the same SfM frame, scaled: every distance between cameras is the unscaled one x the same factor
    ub = {Path(fr.image_path).stem: fr.camera for fr in unscaled.frames}
    s = 0.30 / np.linalg.norm(ub["frame000020"].center - ub["frame000112"].center)
    for a, b in (("frame000146", "frame000166"), ("frame000020", "frame000149")):
        assert np.linalg.norm(by[a].center - by[b].center) == pytest.approx(
            s * np.linalg.norm(ub[a].center - ub[b].center), rel=1e-6)


def test_camera_height_makes_the_frame_metric(sfm, cake_images):
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    work, unscaled, _ = sfm
    res = estimate_poses(load_dataset(cake_images),
                         PoseOptions(work_dir=work, known_length="camera_height=0.45", progress=False))
    f = res.frame
    assert f.source == "table_plane+known_length" and f.scaled and f.scale_uncertainty_rel < 0.05
    h = np.array([c.center[2] for c in res.cameras])
    assert np.mean(h) == pytest.approx(0.45, rel=1e-6) and h.min() > 0.8 * 0.45  # one height band, above
    assert len(res.frames) == len(unscaled.frames) == 8  # all 8 (two via the recover step)


def _composite_marker(frames, out: Path, T_world_marker: np.ndarray, side: float) -> None:
    """Write each photo with an ArUco marker (DICT_4X4_50 id 0, black square `side` units, white quiet
    zone) drawn where a marker lying at T_world_marker would be seen by its camera."""
    import cv2
    from PIL import Image

    from splattwin.scene.marker import TableMarker

    bits = TableMarker(0, 1.0, 0.0, 0.0, 0.0).bitmap()               # [6,6] black border + 4x4 data
    tex = np.pad(bits, 1, constant_values=255)                      # [8,8] with the quiet zone
    tex = cv2.resize(tex, (400, 400), interpolation=cv2.INTER_NEAREST)
    h = side / 2 * 8 / 6                                             # half side of the quiet zone
    local = np.array([[-h, h, 0, 1], [h, h, 0, 1], [h, -h, 0, 1], [-h, -h, 0, 1]])
    corners = (local @ T_world_marker.T)[:, :3]
    src = np.float32([[0, 0], [400, 0], [400, 400], [0, 400]])
    out.mkdir(parents=True)
    for fr in frames:
        cam, path = fr.camera, Path(fr.image_path)
        img = np.asarray(Image.open(path).convert("RGB")).copy()
        uv, _ = cam.project(corners)
        H = cv2.getPerspectiveTransform(src, np.float32(uv))
        warped = cv2.warpPerspective(tex, H, (img.shape[1], img.shape[0]), flags=cv2.INTER_AREA, borderValue=0)
        inside = cv2.warpPerspective(np.full_like(tex, 255), H, (img.shape[1], img.shape[0])) > 127
        img[inside] = warped[inside][:, None]
        Image.fromarray(img).save(out / path.name, quality=95)


def test_marker_on_real_photos(sfm, cake_images, tmp_path):
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.splat.init import look_at_point

    work, unscaled, _ = sfm
    cams = unscaled.cameras
    # a marker on the table plane (z = 0 of the unscaled table frame) below where the cameras look,
    # its side a fifth of the cameras' distance to that point
    target = look_at_point(cams)
    assert target is not None
    dist = float(np.median([np.linalg.norm(c.center - target) for c in cams]))
    side = 0.2 * dist
    T = np.eye(4)
    T[:2, 3] = target[:2]
    photos = tmp_path / "photos"
    _composite_marker(unscaled.frames, photos, T, side)
    # the frames SfM did not register (or dropped) join unchanged: the same image names, so the pose run
    # re-uses the finished SfM model (resume) and only the marker is new
    for p in sorted(cake_images.glob("*.jpg")):
        if not (photos / p.name).exists():
            shutil.copyfile(p, photos / p.name)
    size = 0.08  # metres: the printed marker's side
    res = estimate_poses(load_dataset(photos), PoseOptions(work_dir=work, marker_size=size, progress=False))
    f = res.frame
    assert f.source == "marker" and f.scaled and f.units == "m" and f.scale_uncertainty_rel < 0.05
    assert len(res.stats["marker"]["views"]) == len(unscaled.frames) == 8  # every frame (all registered)
    # metres per SfM unit = size / side: camera distances agree with the unscaled ones times that
    s = size / side
    by = {Path(f.image_path).name: f.camera for f in res.frames}
    fr = unscaled.frames
    assert set(by) == {Path(f.image_path).name for f in fr}
    for a, b in ((fr[0], fr[-1]), (fr[1], fr[-2])):
        d_unscaled = np.linalg.norm(a.camera.center - b.camera.center)
        d_metric = np.linalg.norm(by[Path(a.image_path).name].center - by[Path(b.image_path).name].center)
        assert d_metric == pytest.approx(s * d_unscaled, rel=0.03)
    # the marker frame: its normal is the table's up (z), its centre the origin
    up_unscaled = np.mean([c.center[2] for c in cams]) > 0
    assert up_unscaled and np.mean([c.center[2] for c in res.cameras]) > 0
    T_sfm_table = np.linalg.inv(unscaled.T_out_in)  # both results map the same SfM model
    centre = res.T_out_in @ T_sfm_table @ np.array([*target[:2], 0.0, 1.0])
    assert np.linalg.norm(centre[:3]) < 0.05 * size
