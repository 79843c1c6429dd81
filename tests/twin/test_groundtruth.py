from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from splattwin.errors import InputError
from splattwin.twin.groundtruth import twin_from_scene
from splattwin.twin.manifest import Manifest


def test_gt_twin_reproduces_scene_meshes(scene_small: Path, tmp_path: Path):
    m = twin_from_scene(scene_small, tmp_path / "twin")
    scene = json.loads((scene_small / "scene.json").read_text())
    assert m.frame.scaled and m.frame.source == "ground_truth"
    assert {o.name for o in m.objects} == {o["name"] for o in scene["objects"]}
    assert m.config["target_frame"]["size"] == scene["target_frame"]["size"]
    loaded = Manifest.load(tmp_path / "twin")
    for o in loaded.objects:
        gt = trimesh.load(scene_small / "meshes" / f"{o.name}.ply", force="mesh")
        vis = trimesh.load(tmp_path / "twin" / o.visual_mesh, force="mesh")
        # object-frame mesh placed by T_world_obj is the world-frame GT mesh
        V = vis.vertices @ o.pose[:3, :3].T + o.pose[:3, 3]
        np.testing.assert_allclose(np.sort(V, axis=0), np.sort(gt.vertices, axis=0), atol=1e-6)
        assert o.usable and o.convex_parts and o.mass > 0
        # the convex parts cover the mesh: union of part bounds = mesh bounds
        parts = [trimesh.load(tmp_path / "twin" / p, force="mesh") for p in o.convex_parts]
        lo = np.min([p.bounds[0] for p in parts], axis=0)
        hi = np.max([p.bounds[1] for p in parts], axis=0)
        np.testing.assert_allclose(lo, vis.bounds[0], atol=3e-3)
        np.testing.assert_allclose(hi, vis.bounds[1], atol=3e-3)
        assert all(p.is_convex for p in parts)
    hammer = loaded.object("toy_hammer")
    assert len(hammer.convex_parts) >= 2            # non-convex: decomposed, not one hull
    assert len(loaded.object("blue_box").convex_parts) == 1


def test_gt_twin_rerun_reuses_parts(scene_small: Path, tmp_path: Path):
    twin_from_scene(scene_small, tmp_path)
    part = tmp_path / Manifest.load(tmp_path).object("toy_hammer").convex_parts[0]
    mtime = part.stat().st_mtime_ns
    twin_from_scene(scene_small, tmp_path)
    assert part.stat().st_mtime_ns == mtime


def test_gt_twin_bad_scene(tmp_path: Path):
    with pytest.raises(InputError, match="scene.json"):
        twin_from_scene(tmp_path, tmp_path / "out")
    (tmp_path / "scene.json").write_text(json.dumps({"objects": [{"name": "a", "T_world_obj": np.eye(4).tolist()}]}))
    with pytest.raises(InputError, match="mesh"):
        twin_from_scene(tmp_path, tmp_path / "out")
