"""bench/geometry.py --twin-from on a RUN folder made without training: the capture's measured depth reaches the
conversion as the twin stage gives it (`twin.build.capture_views`), and the tables say whether that carving ran."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin import io


@pytest.fixture(scope="module")
def twin_run(tmp_path_factory) -> Path:
    """A RUN folder as `splattwin demo --out RUN` leaves it, without training: the embedded scene (RUN/scene: depth,
    noisy 2D masks), its capture posed with the scene's poses by the poses stage (RUN/poses: transforms.json with
    the depth maps, frame.json metric), and splats sampled on the ground-truth surfaces with their labels."""
    from splattwin.cli import main
    from splattwin.scene import SceneOptions, generate, synthetic_gaussians
    from splattwin.twin.groundtruth import load_scene_gt

    run = tmp_path_factory.mktemp("geometry_bench")
    scene = generate(run / "scene", SceneOptions(seed=0, width=80, height=60, views=6, heldout=1), progress=False)
    assert main(["poses", str(scene), str(run / "poses"), "--no-progress"]) == 0
    g, labels = synthetic_gaussians(scene, seed=0, density=8000.0)
    g.save_ply(run / "splat" / "point_cloud.ply")
    io.write_npy(run / "semantics" / "labels.npy", labels.astype(np.int32))
    io.write_json(run / "semantics" / "objects.json", [list(o) for o in load_scene_gt(scene)[0]])
    return run


@pytest.mark.slow
def test_twin_from_carves_against_the_captures_depth_as_the_twin_stage(twin_run, load_bench, capsys, tmp_path):
    """--twin-from passed the cameras alone: the capture's depth maps never reached `convert`, so the measured-
    depth carving a build runs (twin.json config.depth_carving) was not what the bench measured. Now the bench
    records the same carving as a twin built from the same splats, cameras and masks, and its mesh table says so."""
    from splattwin.capture import load_dataset
    from splattwin.poses.twin_frame import load_frame
    from splattwin.semantics.options import SemanticsOptions
    from splattwin.semantics.stage import load_stage_masks
    from splattwin.twin.build import build_twin

    assert load_bench("geometry").main(["--twin-from", str(twin_run), "--runs", "1"]) == 0
    out = capsys.readouterr().out
    rec = json.loads(out.strip().splitlines()[-1])
    assert rec["carve_cameras"] == 7 and rec["depth_carving"]["used"] is True
    carved = rec["depth_carving"]["objects"]
    assert carved and all(o["views"] > 0 and o["dropped"] > 0 for o in carved.values())
    dropped, points = sum(o["dropped"] for o in carved.values()), sum(o["points"] for o in carved.values())
    assert f"measured-depth carving: ran ({dropped} of {points} points dropped over {len(carved)} objects)" in out
    assert "ours without measured depth" in out and set(rec["f1_5mm_mesh_no_measured_depth"]) == set(rec["f1_5mm_mesh"])

    # the twin stage, given the same inputs, carves the same points
    frames = load_dataset(twin_run / "poses" / "transforms.json", validate=False, require_images=False).frames
    masks = load_stage_masks(SemanticsOptions(), frames, twin_run / "scene")[0]
    objects = io.read_json(twin_run / "semantics" / "objects.json")
    man = build_twin(twin_run / "splat" / "point_cloud.ply", np.load(twin_run / "semantics" / "labels.npy"), objects,
                     tmp_path / "twin", frame=load_frame(twin_run / "poses"), masks=masks, formats=(), progress=False,
                     cameras_path=twin_run / "poses" / "transforms.json")
    assert man.config["depth_carving"] == rec["depth_carving"]


def test_capture_views_say_why_measured_depth_is_not_used(twin_run, load_bench, tmp_path):
    """A cameras file without frame.json beside it (unscaled: the depth's metres do not apply), or without depth
    maps: no measured depth, and the reason twin.json would record."""
    import shutil

    from splattwin.capture import load_dataset, nerfstudio

    views = load_bench("geometry")._capture_views
    poses = Path(shutil.copytree(twin_run / "poses", tmp_path / "poses", ignore=shutil.ignore_patterns("sfm")))
    (poses / "frame.json").unlink()
    v = views(poses / "transforms.json", twin_run, twin_run / "scene")
    assert v.measured is None and v.depth_skipped.startswith("the twin is unscaled") and len(v.cameras) == 7
    ds = load_dataset(poses / "transforms.json")
    for f in ds.frames:
        f.depth_path = None
    v = views(nerfstudio.write(ds, poses / "no_depth.json"), twin_run, twin_run / "scene")
    assert v.measured is None and v.depth_skipped == "the capture has no depth maps" and v.silhouettes
