"""Free-space carving of splat-extent samples (splattwin.geometry.carving) and its use in the meshes."""

import warnings

import numpy as np
import pytest
import trimesh

from splattwin.capture.camera import Camera, look_at
from splattwin.geometry.carving import depth_views, free_space_mask
from splattwin.geometry.convert import clean_indices, object_geometry
from splattwin.geometry.metrics import mesh_fidelity
from splattwin.geometry.options import GeometryOptions
from splattwin.scene.synthetic import trained_like_gaussians
from splattwin.splat.gaussians import Gaussians


def _down_camera(height: float = 0.5, size=(64, 48)) -> Camera:
    """A camera `height` m above the origin looking straight down (twin frame, z up)."""
    return Camera.from_fov(np.radians(60.0), *size, T_world_cam=look_at([0.0, 0.0, height], [0.0, 0.0, 0.0],
                                                                       up=np.array([0.0, 1.0, 0.0])))


def test_free_space_mask_against_an_analytic_depth_map():
    """A flat depth map 0.5 m below a downward camera (the plane z = 0): points more than tol above the
    plane are free, points on it, below it, outside the image or behind the camera are not; pixels with no
    depth (inf) carve nothing."""
    cam = _down_camera()
    depth = np.full((cam.height, cam.width), 0.5)
    depth[:, :8] = np.inf  # nothing rendered there
    tol = 0.002
    x_nodepth = -0.5 * np.tan(np.radians(30.0)) * 0.9  # projects into the first columns
    pts = np.array([[0.0, 0.0, 0.01],            # 1 cm above the surface: free
                    [0.0, 0.0, 0.0025],          # just beyond tol: free
                    [0.0, 0.0, 0.0015],          # within tol: kept
                    [0.0, 0.0, -0.02],           # behind the surface (inside): kept
                    [x_nodepth, 0.0, 0.01],      # pixel without depth: kept
                    [2.0, 0.0, 0.01],            # outside the image: kept
                    [0.0, 0.0, 0.8]])            # behind the camera: kept
    free = free_space_mask(pts, [(cam, depth)], tol)
    assert free.tolist() == [True, True, False, False, False, False, False]
    # two views: a point is free when any of them sees through it
    side = Camera.from_fov(np.radians(60.0), 64, 48, T_world_cam=look_at([0.5, 0.0, 0.0], [0.0, 0.0, 0.0]))
    far = np.full((48, 64), 10.0)
    assert free_space_mask(pts[[3]], [(cam, depth), (side, far)], tol).tolist() == [True]


def _plane_gaussians(z: float, thick: float, n_side: int = 30, half: float = 0.05) -> Gaussians:
    """Opaque square of flat-ish splats centred at height z, std `thick` along z."""
    xy = np.stack(np.meshgrid(np.linspace(-half, half, n_side), np.linspace(-half, half, n_side)), -1).reshape(-1, 2)
    n = len(xy)
    means = np.column_stack([xy, np.full(n, z)])
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    scales = np.column_stack([np.full(n, 2 * half / n_side), np.full(n, 2 * half / n_side), np.full(n, thick)])
    return Gaussians(means, quats, scales, np.full(n, 0.95), np.full((n, 1, 3), 0.5))


def test_depth_views_render_the_splats_surface_and_cap_the_size():
    """The expected depth of an opaque square at z = 0.02 from 0.5 m above is 0.48 m over the square, inf
    off it; a camera larger than max_side is scaled down with its intrinsics."""
    g = _plane_gaussians(0.02, 0.001)
    big = _down_camera(size=(1280, 960))
    [(cam, depth)] = depth_views(g, [big], max_side=128)
    assert (cam.width, cam.height) == (128, 96) and depth.shape == (96, 128)
    assert np.isclose(cam.fx, big.fx * 0.1)
    # a long video's cameras: at most max_views of them, spread from the first to the last
    ring = [_down_camera(height=0.4 + 0.01 * i) for i in range(10)]
    picked = [c for c, _ in depth_views(g, ring, max_views=3)]
    assert [c.T_world_cam[2, 3] for c in picked] == pytest.approx([0.4, 0.445, 0.49], abs=0.006)
    centre = depth[40:56, 56:72]
    np.testing.assert_allclose(centre, 0.48, atol=1e-4)
    assert np.isinf(depth[0, 0])


def _thick_topped_box():
    """GT box 12 x 8 x 6 cm on z = 0 and trained-like splats on it whose top face splats sit on the
    surface but are thick along the normal (a face seen only from above: nothing constrains their extent
    along the rays), std 0.3-8 mm, median 1.9 mm (as measured on the robot-style capture's twin: 5 / 50 /
    95 % at 0.3 / 1.9 / 5.7 mm), plus cameras looking down at it from a ring above."""
    gt = trimesh.creation.box([0.12, 0.08, 0.06])
    gt.apply_translation([0, 0, 0.03])
    g = trained_like_gaussians(gt, 2000, seed=1)
    rng = np.random.default_rng(0)
    top = (g.means[:, 2] > 0.055) & (g.opacities > 0.5)
    R = g.subset(top).rotation_matrices()
    normal_axis = np.argmax(np.abs(R[:, 2, :]), axis=1)  # the splat axis closest to world z
    s = g.scales[top].copy()
    s[np.arange(len(s)), normal_axis] = np.clip(rng.lognormal(np.log(0.0019), 0.9, len(s)), 0.0003, 0.008)
    g.scales[top] = s
    g.means[top, 2] = 0.06  # centres on the top face
    cams = [Camera.from_fov(np.radians(60.0), 160, 120,
                            T_world_cam=look_at([0.25 * np.cos(a), 0.25 * np.sin(a), 0.45], [0.0, 0.0, 0.03]))
            for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    return gt, g, cams


def _mesh(g, opts, cams):
    labels = np.ones(len(g), dtype=np.int64)
    opts = opts.resolved(1.2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = object_geometry(g, clean_indices(g, labels, 1, opts), "box", 1, opts, support_z=0.0, cameras=cams)
    m = r.visual.copy()
    m.apply_transform(r.T_world_obj)
    return m


def test_carving_brings_a_thick_topped_mesh_down_to_the_surface():
    """Without carving the mesh top stands on the thick splats' envelope (> 5 mm above the 6 cm top);
    with the cameras it is carved to within 3 mm of it and the F1 @ 5 mm rises to >= 0.95; without
    cameras the mesh is the one with carving off."""
    gt, g, cams = _thick_topped_box()
    plain = _mesh(g, GeometryOptions(carve=False), cams)
    no_cams = _mesh(g, GeometryOptions(), None)
    carved = _mesh(g, GeometryOptions(), cams)
    assert np.allclose(plain.bounds, no_cams.bounds)

    def top_height(m):  # median height of the mesh over the inner part of the top face
        v = np.asarray(m.vertices)
        return float(np.median(v[(np.abs(v[:, 0]) < 0.05) & (np.abs(v[:, 1]) < 0.03) & (v[:, 2] > 0.04), 2]))

    assert top_height(plain) > 0.065
    assert abs(top_height(carved) - 0.06) < 0.003
    f_plain, f_carved = mesh_fidelity(plain, gt), mesh_fidelity(carved, gt)
    assert f_carved.f1 > f_plain.f1 + 0.05 and f_carved.f1 >= 0.95, (f_plain, f_carved)
    # nothing is carved into the object: the footprint still covers the truth's (within 1 mm)
    assert np.all(carved.bounds[0, :2] <= gt.bounds[0, :2] + 0.001), carved.bounds
    assert np.all(carved.bounds[1, :2] >= gt.bounds[1, :2] - 0.001), carved.bounds


def test_geometry_command_carves_with_the_cameras_file(tmp_path):
    """`splattwin geometry --cameras transforms.json` (the twin stage's path: build_twin reads the cameras)
    carves the thick top, also when the photos the cameras file names are not there; without --cameras the
    top stays on the envelope."""
    from pathlib import Path

    from splattwin.capture import nerfstudio
    from splattwin.capture.dataset import Dataset, Frame
    from splattwin.cli import main
    from splattwin.twin.manifest import Manifest

    _, box, cams = _thick_topped_box()
    table = _plane_gaussians(0.0, 0.0005, n_side=100, half=0.25)  # the support the twin stage finds first
    g = Gaussians(*(np.concatenate([getattr(table, k), getattr(box, k)]) for k in ("means", "quats", "scales", "opacities")),
                  np.concatenate([np.repeat(table.sh, box.sh.shape[1], axis=1) * 0, box.sh]))
    ply = g.save_ply(tmp_path / "box.ply")
    np.save(tmp_path / "labels.npy", np.r_[np.zeros(len(table), np.int64), np.ones(len(box), np.int64)])
    # the cameras file of splats trained elsewhere: its photos are not here, and carving needs none
    frames = [Frame(image_path=tmp_path / "images" / f"{i:03d}.png", camera=c) for i, c in enumerate(cams)]
    cameras = nerfstudio.write(Dataset(root=tmp_path, frames=frames, has_poses=True), tmp_path / "transforms.json")
    tops = []
    for name, extra in (("plain", []), ("carved", ["--cameras", str(cameras)])):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert main(["geometry", str(ply), "--labels", str(tmp_path / "labels.npy"), "--object", "box=1",
                         "--out", str(tmp_path / name), "--frame", "ground_truth", "--formats", "",
                         "--max-scale", "0.012", *extra]) == 0  # the embedded scene's default (a small scene here)
        obj = Manifest.load(tmp_path / name).object("box")
        m = trimesh.load(tmp_path / name / obj.visual_mesh, process=False)
        m.apply_transform(np.asarray(obj.T_world_obj))
        v = np.asarray(m.vertices)
        tops.append(float(np.median(v[(np.abs(v[:, 0]) < 0.05) & (np.abs(v[:, 1]) < 0.03) & (v[:, 2] > 0.04), 2])))
    assert tops[0] > 0.065 and abs(tops[1] - 0.06) < 0.003, tops


def _box_top_view(cam: Camera, top: float = 0.03, half: float = 0.05):
    """(depth [H,W] m, box mask [H,W], x [H,W]) of a downward camera over a box top at z = `top` (|x|, |y|
    < `half`) on the table z = 0: the z-depth ray-cast, the box's mask, and each pixel's x at the top."""
    d_top = cam.center[2] - top
    p = cam.pixel_rays() * d_top       # camera frame, at the top's depth
    p_world = p.reshape(-1, 3) @ cam.T_world_cam[:3, :3].T + cam.T_world_cam[:3, 3]
    on_box = (np.abs(p_world[:, 0]) < half) & (np.abs(p_world[:, 1]) < half)
    on_box = on_box.reshape(cam.height, cam.width)
    return (np.where(on_box, d_top, cam.center[2]).astype(np.float32), on_box,
            p_world[:, 0].reshape(cam.height, cam.width))


def test_measured_depth_carves_free_space_inside_the_eroded_mask_only():
    """Carving against a sensor's depth (`sensor_views` + `free_space_mask` with the z^2 tolerance and the
    vote): over a box top 3 cm high seen from 0.5 m, samples 1 cm above the top are dropped; samples on
    the top, inside the box, over a hole in the depth (0: no reading), over a pixel that reads 3 cm too
    far (noise), over the part of the top an occluder hides (outside the visible mask; its depth there
    is the occluder's), and on the top's edge where the depth bleeds to the table's are all kept."""
    from splattwin.geometry.carving import measured_views, sensor_views

    cam = _down_camera(0.5, size=(160, 120))
    depth, mask, x_top = _box_top_view(cam)
    top = 0.03

    def pixel(x, y, z=top):
        uv, _ = cam.project(np.array([[x, y, z]]))
        return int(np.floor(uv[0, 1])), int(np.floor(uv[0, 0]))

    hole, noisy = pixel(-0.02, -0.02), pixel(0.0, 0.02)
    depth[hole[0] - 1:hole[0] + 2, hole[1] - 1:hole[1] + 2] = 0.0    # a 3x3 px hole: no reading
    depth[noisy] += 0.03                                              # one reading 3 cm too far
    # an occluder (a gripper finger 20 cm above the table) over the box's +x quarter: not in the box's mask
    occ = mask & (x_top > 0.025)
    depth[occ] = 0.3
    visible = mask & ~occ
    # depth bleeding: the box's outermost two pixels read the table (0.5 m)
    from scipy import ndimage
    ring = mask & ~ndimage.binary_erosion(mask, iterations=2)
    depth[ring] = 0.5

    xs = np.linspace(-0.045, 0.045, 19)
    grid = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    above = np.column_stack([grid, np.full(len(grid), top + 0.01)])
    on_top = np.column_stack([grid, np.full(len(grid), top - 0.0005)])
    inside = np.column_stack([grid, np.full(len(grid), top - 0.015)])
    edge = np.array([[0.048, y, top - 0.0005] for y in np.linspace(-0.04, 0.04, 9)]
                    + [[x, -0.048, top - 0.0005] for x in np.linspace(-0.04, 0.02, 7)])
    hole_pt = np.array([[-0.02, -0.02, top + 0.01]])
    noisy_pt = np.array([[0.0, 0.02, top - 0.0005]])
    pts = np.concatenate([above, on_top, inside, edge, hole_pt, noisy_pt])

    views = measured_views([(cam, visible)], lambda c: depth)
    free = free_space_mask(pts, views, 0.002, 0.01, 0.5)
    n = len(grid)
    under_occluder = above[:, 0] > 0.025 - 0.015   # the occluded quarter and its margin (a depth edge: 3 px off)
    over_hole = np.abs(above[:, :2] + 0.02).max(axis=1) < 0.006
    # 1 cm above the top, away from the occluded quarter, the hole and the depth edges: all free
    interior = ~under_occluder & ~over_hole & (np.abs(above[:, :2]).max(axis=1) < 0.03)
    assert interior.sum() > 50 and free[:n][interior].all(), above[interior & ~free[:n]]
    assert not free[:n][above[:, 0] > 0.03].any()           # under the occluder: kept
    assert not free[n:3 * n].any()                          # on the top, inside the box: kept
    assert not free[3 * n:3 * n + len(edge)].any()          # at the bleeding edge: kept
    assert not free[-2] and not free[-1]                    # over the hole; at the noisy pixel
    # the filter and the erosion are what keep them: the raw depth under the full mask carves those
    raw = np.where(mask & np.isfinite(depth) & (depth > 0), depth, np.inf)
    free_raw = free_space_mask(pts, [(cam, raw)], 0.002, 0.01, 0.5)
    assert free_raw[-1] and free_raw[3 * n:3 * n + len(edge)].any()
    # sensor_views: inf outside the eroded visible mask and at holes
    sv = sensor_views(depth, visible)
    assert np.isinf(sv[~visible]).all() and np.isinf(sv[hole]) and abs(sv[noisy] - (0.5 - top)) < 1e-6


def test_measured_depth_keeps_the_silhouette_under_an_overshooting_mask(monkeypatch):
    """A segmenter's mask 8 px larger than the box (perfect depth): a pixel on the box's silhouette reads
    the table behind the box's edge, and the mask's erosion does not reach it; the depth edge it sits on
    does, so the box's points there are kept (without the edge rule they are carved)."""
    from scipy import ndimage

    from splattwin.geometry import carving

    cam = _down_camera(0.5, size=(160, 120))
    depth, mask, _ = _box_top_view(cam)
    loose = ndimage.binary_dilation(mask, iterations=8)
    top = 0.03
    s = np.linspace(-0.045, 0.045, 31)
    rim = np.concatenate([np.column_stack([np.full_like(s, sx * 0.0499), s, np.full_like(s, top - 0.0005)])
                          for sx in (-1, 1)]
                         + [np.column_stack([s, np.full_like(s, sy * 0.0499), np.full_like(s, top - 0.0005)])
                            for sy in (-1, 1)])
    views = carving.measured_views([(cam, loose)], lambda c: depth)
    assert not free_space_mask(rim, views, 0.002, 0.005, 0.5).any()
    monkeypatch.setattr(carving, "DEPTH_EDGE", np.inf)
    views = carving.measured_views([(cam, loose)], lambda c: depth)
    assert free_space_mask(rim, views, 0.002, 0.005, 0.5).sum() >= 5


def test_measured_depth_that_would_carve_most_of_an_object_carves_nothing(caplog):
    """Depth that sees most of an object's points as free space disagrees with the twin (a wrong depth
    scale, poses, another object's mask): nothing is dropped, a warning says so, and the object records 0
    dropped of its points; the true depth drops the one point above the top, and records it."""
    from splattwin.geometry.convert import ObjectGeometry, _carve_measured

    cam = _down_camera(0.5, size=(160, 120))
    depth, mask, _ = _box_top_view(cam)
    xs = np.linspace(-0.02, 0.02, 9)
    pts = np.column_stack([np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2), np.full(81, 0.0295)])
    opts = GeometryOptions()
    far = [(cam, np.where(mask, depth + 0.1, np.inf).astype(np.float32))]    # depth read 10 cm too far
    out = ObjectGeometry(name="box", label=1)
    with caplog.at_level("WARNING"):
        kept = _carve_measured(pts, far, opts, "box", out)
    assert len(kept) == len(pts) and out.depth_carved == 0 and out.depth_points == 81 and out.depth_views == 1
    assert "not carved against it" in caplog.text
    # one point 1.5 cm above the top: dropped, the rest kept
    pts2 = np.concatenate([pts, [[0.0, 0.0, 0.045]]])
    out2 = ObjectGeometry(name="box", label=1)
    kept2 = _carve_measured(pts2, [(cam, np.where(mask, depth, np.inf).astype(np.float32))], opts, "box", out2)
    assert len(kept2) == 81 and out2.depth_carved == 1
