"""A tiny synthetic twin for the playback tests: a textured table of flat Gaussians (label 0) and one
box-shaped object of Gaussians with view-dependent colour (label 1), its splats.ply in the object
frame, and two capture cameras in poses/transforms.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.capture.camera import Camera, look_at
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0

TABLE_HALF = 0.2
OBJ_CENTRE = np.array([0.03, -0.02, 0.025])
OBJ_HALF = np.array([0.025, 0.02, 0.025])


def table_colour(xy: np.ndarray) -> np.ndarray:
    """A smooth two-colour pattern (the hole fill must continue it)."""
    u = 0.5 + 0.5 * np.sin(xy[:, 0] * 60.0) * np.cos(xy[:, 1] * 45.0)
    return np.stack([0.55 + 0.3 * u, 0.45 + 0.1 * u, 0.3 + 0.05 * u], 1)


def make_table(spacing: float = 0.004) -> Gaussians:
    g = np.arange(-TABLE_HALF, TABLE_HALF + 1e-9, spacing)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    xy = np.stack([xx.ravel(), yy.ravel()], 1)
    xy = xy[~np.all(np.abs(xy - OBJ_CENTRE[:2]) < OBJ_HALF[:2] - 0.002, axis=1)]   # never seen: under the box
    n = len(xy)
    means = np.concatenate([xy, np.zeros((n, 1))], 1)
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = rgb_to_sh0(table_colour(xy))
    return Gaussians(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.tile([spacing * 0.7, spacing * 0.7, 1e-4], (n, 1)),
                     np.full(n, 0.95), sh)


def make_object(n: int = 1500, seed: int = 1) -> Gaussians:
    """Gaussians on the faces of a box centred at OBJ_CENTRE (world), degree-3 SH."""
    rng = np.random.default_rng(seed)
    face = rng.integers(0, 5, n)   # no bottom face
    uv = rng.uniform(-1, 1, (n, 2))
    p = np.zeros((n, 3))
    axes = [(0, 1, 2, 1), (0, 1, 2, -1), (1, 2, 0, 1), (1, 2, 0, -1), (0, 2, 1, 1)]
    for k, (a, b, c, s) in enumerate(axes):
        m = face == k
        p[m, a] = uv[m, 0] * OBJ_HALF[a]
        p[m, b] = uv[m, 1] * OBJ_HALF[b]
        p[m, c] = s * OBJ_HALF[c]
    p[face == 0, 2] = OBJ_HALF[2]   # top
    p[face == 1, 2] = OBJ_HALF[2] * uv[face == 1, 1]
    p[face == 1, 1] = -OBJ_HALF[1]
    means = p + OBJ_CENTRE
    sh = rng.normal(0, 0.25, (n, 16, 3))
    sh[:, 0] = rgb_to_sh0(np.array([0.15, 0.3, 0.85]) + rng.normal(0, 0.03, (n, 3)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(means, q, np.full((n, 3), 0.004), np.full(n, 0.9), sh)


def capture_cameras(width: int = 96, height: int = 72) -> list[Camera]:
    eyes = [np.array([-0.35, -0.25, 0.35]), np.array([0.3, 0.3, 0.3])]
    return [Camera.from_fov(np.radians(55), width, height, look_at(e, np.array([0.0, 0.0, 0.02])), name=f"view_{i}")
            for i, e in enumerate(eyes)]


def write_twin(out: Path, with_splats: bool = True) -> Path:
    from splattwin import io
    from splattwin.capture.dataset import Dataset, Frame
    from splattwin.capture.nerfstudio import write as write_transforms
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import Background, Manifest, ObjectEntry
    from splattwin.twin.splats import write_object_splats

    table, obj = make_table(), make_object()
    full = Gaussians(np.concatenate([table.means, obj.means]), np.concatenate([table.quats, obj.quats]),
                     np.concatenate([table.scales, obj.scales]), np.concatenate([table.opacities, obj.opacities]),
                     np.concatenate([table.sh, obj.sh]))
    labels = np.concatenate([np.zeros(len(table), np.int32), np.ones(len(obj), np.int32)])
    T0 = np.eye(4)
    T0[:3, 3] = OBJ_CENTRE
    entry = ObjectEntry(name="blue_box", label=1, T_world_obj=T0.tolist(), bbox_extent=(2 * OBJ_HALF).tolist(),
                        usable=True)
    if with_splats:
        full.save_ply(out / "splat" / "point_cloud.ply")
        io.write_npy(out / "semantics" / "labels.npy", labels)
        write_object_splats(out / "objects" / "blue_box" / "splats.ply", obj, T0)
        entry.splat_ply = "objects/blue_box/splats.ply"
    cams = capture_cameras()
    frames = []
    for c in cams:
        img = out / "poses" / "images" / f"{c.name}.png"
        io.write_image(img, np.zeros((c.height, c.width, 3), np.uint8))
        frames.append(Frame(image_path=img, camera=c))
    write_transforms(Dataset(root=out / "poses", frames=frames, has_poses=True), out / "poses" / "transforms.json")
    m = Manifest(frame=TwinFrame(source="ground_truth", scaled=True), objects=[entry],
                 background=Background(table_height=0.0, table_extent=[-TABLE_HALF, TABLE_HALF, -TABLE_HALF, TABLE_HALF]),
                 cameras="poses/transforms.json",
                 splats="splat/point_cloud.ply" if with_splats else None,
                 labels="semantics/labels.npy" if with_splats else None)
    m.save(out)
    return out


@pytest.fixture(scope="session")
def tiny_twin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_twin(tmp_path_factory.mktemp("tiny_twin"))


@pytest.fixture(scope="session")
def meshonly_twin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_twin(tmp_path_factory.mktemp("meshonly_twin"), with_splats=False)


def add_splats_to_gt_twin(twin: Path, per_object: int = 1200, table_spacing: float = 0.01, seed: int = 0) -> Path:
    """Give a ground-truth twin (meshes, no splats; `twin.groundtruth.twin_from_scene`) splats: Gaussians
    on each usable object's visual mesh in its label colour, and a textured table, with the labels and
    per-object splats.ply the semantics and twin stages would write. Physics runs on the meshes as before."""
    import trimesh

    from splattwin import io
    from splattwin.meshio import load_mesh
    from splattwin.twin.manifest import Manifest
    from splattwin.twin.splats import write_object_splats

    rng = np.random.default_rng(seed)
    man = Manifest.load(twin)
    bg = man.background
    x0, x1, y0, y1 = (float(v) for v in bg.table_extent)
    gx, gy = np.meshgrid(np.arange(x0, x1, table_spacing), np.arange(y0, y1, table_spacing), indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    n = len(xy)
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = rgb_to_sh0(table_colour(xy))
    parts = [Gaussians(np.c_[xy, np.full(n, bg.table_height)], np.tile([1.0, 0, 0, 0], (n, 1)),
                       np.tile([table_spacing * 0.7, table_spacing * 0.7, 1e-4], (n, 1)), np.full(n, 0.95), sh)]
    labels = [np.zeros(n, np.int32)]
    palette = np.array([[0.15, 0.3, 0.85], [0.9, 0.8, 0.1], [0.6, 0.45, 0.3], [0.8, 0.2, 0.2], [0.2, 0.7, 0.3]])
    for k, o in enumerate(man.objects):
        if not o.usable:
            continue
        m = load_mesh(twin / o.visual_mesh, o.name)
        tm = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=False)
        pts, _ = trimesh.sample.sample_surface(tm, per_object, seed=seed + k)
        T = o.pose
        world = pts @ T[:3, :3].T + T[:3, 3]
        sh = np.zeros((len(pts), 16, 3))
        sh[:, 0] = rgb_to_sh0(np.clip(palette[k % len(palette)] + rng.normal(0, 0.03, (len(pts), 3)), 0, 1))
        g = Gaussians(world, np.tile([1.0, 0, 0, 0], (len(pts), 1)), np.full((len(pts), 3), 0.005),
                      np.full(len(pts), 0.9), sh)
        rel = f"objects/{o.name}/splats.ply"
        write_object_splats(twin / rel, g, T)
        o.splat_ply = rel
        parts.append(g)
        labels.append(np.full(len(pts), o.label, np.int32))
    full = Gaussians(*(np.concatenate([getattr(p, a) for p in parts])
                       for a in ("means", "quats", "scales", "opacities", "sh")))
    full.save_ply(twin / "splat" / "point_cloud.ply")
    io.write_npy(twin / "semantics" / "labels.npy", np.concatenate(labels))
    man.splats, man.labels = "splat/point_cloud.ply", "semantics/labels.npy"
    man.save(twin)
    return twin


@pytest.fixture(scope="session")
def splat_gt_twin(scene_small: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small embedded scene's ground-truth twin with synthetic splats (`add_splats_to_gt_twin`)."""
    from splattwin.twin.groundtruth import twin_from_scene

    import shutil

    from splattwin.twin.manifest import Manifest

    out = tmp_path_factory.mktemp("splat_gt_twin")
    twin_from_scene(scene_small, out)
    # the capture cameras, as the poses stage leaves them
    shutil.copytree(scene_small / "images", out / "poses" / "images")
    shutil.copy(scene_small / "transforms.json", out / "poses" / "transforms.json")
    man = Manifest.load(out)
    man.cameras = "poses/transforms.json"
    man.save(out)
    return add_splats_to_gt_twin(out)
