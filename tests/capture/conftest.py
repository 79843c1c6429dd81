from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import Camera, Dataset, Frame, look_at


def make_dataset(root: Path, n: int = 4, w: int = 64, h: int = 48, dist=None, per_frame_K: bool = False,
                 with_points: bool = True, with_depth: bool = False) -> Dataset:
    """Small posed dataset on disk: random images, cameras on a circle looking at the origin."""
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        a = 2 * np.pi * i / n
        T = look_at(np.array([0.6 * np.cos(a), 0.6 * np.sin(a), 0.4]), np.zeros(3))
        f = 50.0 + (i if per_frame_K else 0)
        K = np.array([[f, 0, w / 2 + 0.5], [0, f * 1.01, h / 2 - 0.25], [0, 0, 1]])
        img = root / "images" / f"img_{i:03d}.png"
        io.write_image(img, rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        depth = None
        if with_depth:
            depth = root / "depth" / f"img_{i:03d}.npy"
            io.write_npy(depth, rng.uniform(0.3, 1.0, (h, w)).astype(np.float32))
        frames.append(Frame(image_path=img, camera=Camera(K=K, width=w, height=h, T_world_cam=T, dist=dist, name=img.stem),
                            depth_path=depth, split="heldout" if i == n - 1 else "train"))
    xyz = rng.normal(size=(20, 3)) if with_points else None
    rgb = rng.integers(0, 255, (20, 3), dtype=np.uint8) if with_points else None
    return Dataset(root=root, frames=frames, has_poses=True, points_xyz=xyz, points_rgb=rgb)


@pytest.fixture(name="make_dataset")
def make_dataset_fixture():
    """The `make_dataset(root, ...)` builder, as a fixture (tests import nothing from conftest)."""
    return make_dataset
