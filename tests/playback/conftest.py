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
