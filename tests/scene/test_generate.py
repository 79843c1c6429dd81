from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from splattwin.capture.camera import opencv_from_opengl
from splattwin.errors import InputError
from splattwin.scene import SceneOptions, generate, load_scene, scene_cameras

OBJECTS = ["cardboard_box", "blue_box", "yellow_cube", "toy_hammer", "bottle"]


def _labels(scene_dir: Path, view: str) -> np.ndarray:
    return np.array(Image.open(scene_dir / "masks" / "gt" / f"{view}.png"))


def test_layout_on_disk(scene_small):
    d = scene_small
    tj = json.loads((d / "transforms.json").read_text())
    scene = load_scene(d)
    views = scene["views"]
    assert len(views) == 11 and len(tj["frames"]) == 11
    assert len(tj["train_filenames"]) == 8 and len(tj["test_filenames"]) == 3
    for f in tj["frames"]:
        view = Path(f["file_path"]).stem
        assert f["split"] == ("heldout" if view.startswith("heldout") else "train")
        img = np.array(Image.open(d / f["file_path"]))
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8
        depth = np.load(d / f["depth_file_path"])
        assert depth.shape == (120, 160) and depth.dtype == np.float32
        assert np.all((depth > 0.1) | np.isinf(depth))
        lab = np.array(Image.open(d / f["label_path"]))
        assert lab.shape == (120, 160) and lab.dtype == np.uint8 and lab.max() <= 5
        for obj in OBJECTS:
            m = np.array(Image.open(d / "masks" / "noisy" / view / f"{obj}.png"))
            assert m.shape == (120, 160) and set(np.unique(m)) <= {0, 255}
    assert [o["name"] for o in scene["objects"]] == OBJECTS
    for o in scene["objects"]:
        assert (d / o["mesh"]).is_file() and o["label"] in range(1, 6)
        assert {"prompt", "kind", "T_world_obj", "extent", "convex"} <= set(o)
    assert (d / "meshes" / "table.ply").is_file() and (d / scene["preview"]).is_file()
    assert scene["marker"] is None and scene["target_frame"]["size"] > 0.2
    assert {"p_miss", "p_bleed", "p_blob", "p_partial", "events"} <= set(scene["noise"])
    # every object is seen in most views
    seen = {o: 0 for o in range(1, 6)}
    for v in views:
        lab = _labels(d, v)
        for o in seen:
            seen[o] += int((lab == o).sum() > 10)
    assert min(seen.values()) >= 0.6 * len(views), seen


def test_cameras_arc_and_heldout_interleaved(scene_small):
    cams = scene_cameras(scene_small)
    names = [c.name for c in cams]
    assert names[0].startswith("train") and names[-1].startswith("train")
    assert sum(n.startswith("heldout") for n in names) == 3
    for c in cams:
        dist = np.linalg.norm(c.center)
        assert 0.45 <= dist <= 0.8
        assert c.center[2] > 0.2
        # optical axis points down towards the table
        assert c.T_world_cam[2, 2] < -0.3
    tj = json.loads((scene_small / "transforms.json").read_text())
    for f, c in zip(tj["frames"], cams):
        np.testing.assert_allclose(opencv_from_opengl(np.array(f["transform_matrix"])), c.T_world_cam)


def test_gt_mesh_vertices_project_into_gt_masks(scene_small):
    """Surface points of every GT mesh, projected through the written cameras, land in that object's GT
    label wherever the GT depth says they are visible."""
    d = scene_small
    scene = load_scene(d)
    cams = scene_cameras(d)
    total_vis = total_in = 0
    for o in scene["objects"]:
        mesh = trimesh.load(d / o["mesh"], process=False)
        pts = np.vstack([mesh.vertices, trimesh.sample.sample_surface_even(mesh, 3000, seed=1)[0]])
        # within a few mm of the table contact a depth test cannot tell object from table: leave those out
        pts = pts[pts[:, 2] > 3e-3]
        for cam in cams:
            uv, z = cam.project(pts)
            ok = cam.in_image(uv)
            ij = np.floor(uv[ok]).astype(int)
            depth = np.load(d / "depth" / f"{cam.name}.npy")
            lab = _labels(d, cam.name)
            dz = depth[ij[:, 1], ij[:, 0]]
            # visible: the pixel's depth is (within the depth change across one pixel) that of the point
            vis = np.abs(dz - z[ok]) < 2e-3
            inside = lab[ij[vis, 1], ij[vis, 0]] == o["label"]
            total_vis += int(vis.sum())
            total_in += int(inside.sum())
    assert total_vis > 2000
    assert total_in / total_vis >= 0.99, total_in / total_vis


def test_depth_agrees_with_independent_ray_mesh_intersection(scene_small):
    d = scene_small
    meshes = [trimesh.load(p, process=False) for p in sorted((d / "meshes").glob("*.ply"))]
    world = trimesh.util.concatenate(meshes)
    rmi = trimesh.ray.ray_triangle.RayMeshIntersector(world)
    rng = np.random.default_rng(0)
    for cam in scene_cameras(d)[:3]:
        depth = np.load(d / "depth" / f"{cam.name}.npy")
        ij = np.stack([rng.integers(0, cam.width, 150), rng.integers(0, cam.height, 150)], axis=1)
        pix = np.concatenate([ij + 0.5, np.ones((len(ij), 1))], axis=1)
        d_cam = pix @ np.linalg.inv(cam.K).T
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        d_world = d_cam @ cam.T_world_cam[:3, :3].T
        o_world = np.broadcast_to(cam.center, d_world.shape)
        locs, ray_idx, _ = rmi.intersects_location(o_world, d_world, multiple_hits=True)
        ray_len = np.full(len(ij), np.inf)
        for loc, r in zip(locs, ray_idx):
            ray_len[r] = min(ray_len[r], np.linalg.norm(loc - cam.center))
        z_expected = ray_len * d_cam[:, 2]
        z = depth[ij[:, 1], ij[:, 0]]
        assert np.array_equal(np.isinf(z), np.isinf(z_expected))
        fin = np.isfinite(z)
        assert fin.sum() > 100
        np.testing.assert_allclose(z[fin], z_expected[fin], atol=2e-4)


def test_target_frame_tape_is_printed_where_recorded(scene_small):
    scene = load_scene(scene_small)
    tf = scene["target_frame"]
    c, h = np.array(tf["center"]), tf["size"] / 2
    t = np.linspace(-h, h, 60)
    line = np.concatenate([np.stack([c[0] + t, c[1] + s * h + 0 * t, 0 * t], 1) for s in (-1, 1)] +
                          [np.stack([c[0] + s * h + 0 * t, c[1] + t, 0 * t], 1) for s in (-1, 1)])
    cols = []
    for cam in scene_cameras(scene_small):
        img = np.asarray(Image.open(scene_small / "images" / f"{cam.name}.png"), dtype=np.float64) / 255
        depth = np.load(scene_small / "depth" / f"{cam.name}.npy")
        uv, z = cam.project(line)
        ok = cam.in_image(uv)
        ij = np.floor(uv[ok]).astype(int)
        vis = np.abs(depth[ij[:, 1], ij[:, 0]] - z[ok]) < 2e-3
        cols.append(img[ij[vis, 1], ij[vis, 0]])
    cols = np.concatenate(cols)
    assert len(cols) > 100
    # orange tape: blue/red ratio (shading-invariant) far below the wood's (~0.5) on the centre line
    assert np.mean(cols[:, 2] < 0.25 * cols[:, 0]) > 0.9
    # and 3 cm inside the frame it is wood, not tape (the tape is a thin outline)
    inner = np.concatenate([np.stack([c[0] + t * 0.7, c[1] + s * (h - 0.03) + 0 * t, 0 * t], 1) for s in (-1, 1)])
    cam = scene_cameras(scene_small)[0]
    img = np.asarray(Image.open(scene_small / "images" / f"{cam.name}.png"), dtype=np.float64) / 255
    uv, _ = cam.project(inner)
    ok = cam.in_image(uv)
    lab = _labels(scene_small, cam.name)
    ij = np.floor(uv[ok]).astype(int)
    on_table = lab[ij[:, 1], ij[:, 0]] == 0
    px = img[ij[on_table, 1], ij[on_table, 0]]
    assert len(px) > 20 and np.mean(px[:, 2] > 0.3 * px[:, 0]) > 0.8


def test_images_are_textured_for_feature_matching(scene_small):
    """SIFT finds features and matches between neighbouring views, and the matches obey the epipolar
    geometry of the written cameras (texture is real surface texture, not view-dependent noise)."""
    cams = scene_cameras(scene_small)[:2]
    sift = cv2.SIFT_create()
    feats = []
    for cam in cams:
        img = np.array(Image.open(scene_small / "images" / f"{cam.name}.png").convert("L"))
        kp, desc = sift.detectAndCompute(img, None)
        assert len(kp) > 60
        feats.append((np.array([k.pt for k in kp]), desc))
    pairs = cv2.BFMatcher().knnMatch(feats[0][1], feats[1][1], k=2)
    good = [m for m, n in pairs if m.distance < 0.75 * n.distance]
    x0 = feats[0][0][[m.queryIdx for m in good]]
    x1 = feats[1][0][[m.trainIdx for m in good]]
    # fundamental matrix from the GT poses; SIFT's keypoint coordinates put pixel centres at integers
    T_10 = cams[1].T_cam_world @ cams[0].T_world_cam
    R, t = T_10[:3, :3], T_10[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(cams[1].K).T @ tx @ R @ np.linalg.inv(cams[0].K)
    h0 = np.concatenate([x0 + 0.5, np.ones((len(x0), 1))], axis=1)
    h1 = np.concatenate([x1 + 0.5, np.ones((len(x1), 1))], axis=1)
    l1 = h0 @ F.T
    dist = np.abs(np.sum(h1 * l1, axis=1)) / np.linalg.norm(l1[:, :2], axis=1)
    inliers = dist < 1.5
    # 160x120 views ~20 degrees apart: few but correct matches (at 320x240 SfM registers every view)
    assert inliers.sum() >= 10 and inliers.mean() > 0.7, (inliers.sum(), inliers.mean())


def _tree_hash(d: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(d.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(d)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_determinism_byte_identical(tmp_path):
    opts = SceneOptions(seed=3, width=64, height=48, views=3, heldout=1, marker=True)
    a = generate(tmp_path / "a", opts, progress=False)
    b = generate(tmp_path / "b", opts, progress=False)
    assert len(list(a.rglob("*.png"))) == 4 + 4 + 4 * 5 + 1  # images, GT, noisy, preview
    assert _tree_hash(a) == _tree_hash(b)
    c = generate(tmp_path / "c", SceneOptions(seed=4, width=64, height=48, views=3, heldout=1), progress=False)
    assert _tree_hash(a) != _tree_hash(c)


def test_marker_is_detectable_where_recorded(tmp_path):
    d = generate(tmp_path / "m", SceneOptions(seed=0, views=4, heldout=0, marker=True), progress=False)
    scene = load_scene(d)
    mk = scene["marker"]
    assert mk["id"] == 0 and mk["dictionary"] == "DICT_4X4_50" and mk["size"] == 0.08
    corners_world = np.array(mk["corners_world"])
    np.testing.assert_allclose(corners_world[:, 2], 0.0)
    np.testing.assert_allclose(np.linalg.norm(corners_world[1] - corners_world[0]), 0.08)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    found = 0
    for cam in scene_cameras(d):
        img = cv2.imread(str(d / "images" / f"{cam.name}.png"), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = det.detectMarkers(img)
        uv, _ = cam.project(corners_world)
        if ids is None or 0 not in ids.ravel():
            continue
        found += 1
        c = corners[list(ids.ravel()).index(0)][0] + 0.5  # OpenCV detector: pixel centres at integers
        # detected corners = recorded corners, in OpenCV order (a wrong order/size would be >10 px off)
        assert np.abs(c - uv).max() < 2.0
    assert found >= 2


@pytest.mark.parametrize("kw", [dict(width=-5), dict(height=0), dict(views=0), dict(heldout=-1),
                                dict(marker_size=-0.1), dict(seed=-1), dict(supersample=0), dict(supersample=9)])
def test_bad_options_raise_input_error(tmp_path, kw):
    with pytest.raises(InputError):
        generate(tmp_path / "x", SceneOptions(**kw), progress=False)
    assert not (tmp_path / "x" / "scene.json").exists()


def test_output_path_that_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        generate(f, SceneOptions(width=32, height=32, views=1, heldout=0), progress=False)


def test_regenerating_into_a_folder_removes_stale_views(tmp_path):
    out = tmp_path / "s"
    generate(out, SceneOptions(width=48, height=40, views=4, heldout=2), progress=False)
    (out / "notes.txt").write_text("mine")
    generate(out, SceneOptions(width=48, height=40, views=2, heldout=1), progress=False)
    assert sorted(p.stem for p in (out / "images").glob("*.png")) == ["heldout_000", "train_000", "train_001"]
    assert sorted(p.stem for p in (out / "depth").glob("*.npy")) == ["heldout_000", "train_000", "train_001"]
    assert sorted(p.name for p in (out / "masks" / "noisy").iterdir()) == ["heldout_000", "train_000", "train_001"]
    assert (out / "notes.txt").read_text() == "mine"  # not ours: left alone
    assert len(load_scene(out)["views"]) == 3


@pytest.mark.parametrize("doc", [[1, 2], "scene", {"fl_x": 1}], ids=["list", "text", "missing-keys"])
def test_malformed_scene_files_are_input_errors_naming_them(tmp_path, doc):
    """A scene.json holding a list raised TypeError from load_scene, a transforms.json without the scene's
    keys KeyError from scene_cameras, and both read the whole file whatever its size (audit 10A L13)."""
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"scene\.json: "):
        load_scene(tmp_path)
    with pytest.raises(InputError, match=r"transforms\.json: "):
        scene_cameras(tmp_path)


def test_scene_files_are_read_bounded(scene_small, monkeypatch):
    from splattwin import limits

    monkeypatch.setattr(limits, "MAX_JSON_BYTES", 64)
    with pytest.raises(InputError, match=r"scene\.json"):
        load_scene(scene_small)
    with pytest.raises(InputError, match=r"transforms\.json"):
        scene_cameras(scene_small)
