import warnings

import numpy as np
import pytest

from splattwin.cli import build_parser, main
from splattwin.scene.synthetic import synthetic_scene
from splattwin.twin.manifest import Manifest


@pytest.mark.parametrize("cmd", [["geometry", "--help"], ["export", "--help"]])
def test_help(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(cmd)
    assert e.value.code == 0 and "usage" in capsys.readouterr().out


def test_geometry_cli_builds_twin(tmp_path):
    g, labels, objects, _ = synthetic_scene(8000, seed=2)
    ply = g.save_ply(tmp_path / "scene.ply")
    np.save(tmp_path / "labels.npy", labels)
    out = tmp_path / "twin"
    (tmp_path / "transforms.json").write_text("{}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["geometry", str(ply), "--labels", str(tmp_path / "labels.npy"), "--object", "box=1:blue box",
                   "--object", "hammer=3", "--out", str(out), "--frame", "ground_truth", "--formats", "urdf",
                   "--cameras", str(tmp_path / "transforms.json")])
    assert rc == 0
    m = Manifest.load(out)
    assert [o.name for o in m.objects] == ["box", "hammer"] and all(o.usable for o in m.objects)
    assert m.object("box").prompt == "blue box" and m.frame.scaled
    # a cameras file outside the twin is recorded as a reference, never as a path in twin.json (relocatable)
    assert m.cameras is None and m.config["cameras_source"] == str((tmp_path / "transforms.json").resolve())
    assert (out / "export" / "scene.urdf").is_file() and "urdf" in m.exports and "mjcf" not in m.exports


def test_geometry_cli_no_progress_prints_no_progress_line(tmp_path, capsys):
    """`geometry --no-progress`: none of the "geometry: 0/N part" lines a log gets without it (audit 9 F2)."""
    g, labels, _, _ = synthetic_scene(4000, seed=2)
    ply = g.save_ply(tmp_path / "scene.ply")
    np.save(tmp_path / "labels.npy", labels)
    argv = ["geometry", str(ply), "--labels", str(tmp_path / "labels.npy"), "--object", "box=1", "--formats", "",
            "--frame", "ground_truth", "--voxel-remesh"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(argv + ["--out", str(tmp_path / "with")]) == 0
        assert "geometry: 0/" in capsys.readouterr().err   # the line the flag must silence
        assert main(argv + ["--out", str(tmp_path / "without"), "--no-progress"]) == 0
    out = capsys.readouterr()
    assert "geometry: " not in out.err + out.out and "twin written to" in out.out


def test_geometry_cli_bad_input(tmp_path):
    g, labels, _, _ = synthetic_scene(4000, seed=3)
    ply = g.save_ply(tmp_path / "scene.ply")
    np.save(tmp_path / "short.npy", labels[:10])
    assert main(["geometry", str(tmp_path / "nope.ply"), "--out", str(tmp_path / "t")]) == 2
    assert main(["geometry", str(ply), "--labels", str(tmp_path / "short.npy"), "--out", str(tmp_path / "t")]) == 2
    assert main(["geometry", str(ply), "--object", "bad", "--labels", str(tmp_path / "short.npy"),
                 "--out", str(tmp_path / "t")]) == 2


def test_geometry_cli_refuses_labels_that_are_not_one_per_gaussian(tmp_path, capsys):
    g, labels, _, _ = synthetic_scene(4000, seed=3)
    ply = g.save_ply(tmp_path / "scene.ply")
    for name, arr in (("row.npy", labels[None, :]), ("col.npy", labels[:, None])):
        np.save(tmp_path / name, arr)
        assert main(["geometry", str(ply), "--labels", str(tmp_path / name), "--out", str(tmp_path / "t")]) == 2
        assert "1-D array" in capsys.readouterr().err
    assert not (tmp_path / "t" / "twin.json").exists()


def test_geometry_cli_evaluates_against_a_generated_scene(tmp_path, scene_small):
    import json

    from splattwin.scene import synthetic_gaussians

    g, labels = synthetic_gaussians(scene_small, seed=1, density=20000.0)
    ply = g.save_ply(tmp_path / "s.ply")
    np.save(tmp_path / "l.npy", labels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["geometry", str(ply), "--labels", str(tmp_path / "l.npy"), "--out", str(tmp_path / "t"),
                   "--formats", "", "--gt-scene", str(scene_small), "--voxel-remesh"])
    assert rc == 0
    ab = json.loads((tmp_path / "t" / "geometry_ablation.json").read_text())
    assert set(ab) == {"raw", "attribute", "cluster", "full"}
    assert len(ab["full"]) == len(np.unique(labels[labels > 0]))
    assert all(0.0 <= v["f1"] <= 1.0 for v in ab["full"].values())
    assert main(["geometry", str(ply), "--labels", str(tmp_path / "l.npy"), "--out", str(tmp_path / "t2"),
                 "--formats", "", "--gt-scene", str(tmp_path)]) == 2


def test_geometry_cli_masks_tell_a_small_whole_object_from_a_fragment(tmp_path, capsys):
    """`splattwin geometry --masks` (the twin stage's path: build_twin with the 2D masks): a 2.5 cm cube
    with 48 splats (< min_points 50) is usable because its splats cover its masks; 35 splats at one end of
    a 19 cm bar are not (a fragment: the problem names the coverage); twin.json records both figures.
    Without --masks the cube is unusable by the count alone."""
    import trimesh
    from scipy.spatial import ConvexHull
    from skimage.draw import polygon

    from splattwin.capture import nerfstudio
    from splattwin.capture.camera import Camera, look_at
    from splattwin.capture.dataset import Dataset, Frame
    from splattwin.scene.synthetic import trained_like_gaussians
    from splattwin.semantics.masks import MaskSet
    from splattwin.splat.gaussians import Gaussians

    cube = trimesh.creation.box([0.025] * 3)
    cube.apply_translation([-0.08, 0.0, 0.0125])
    bar = trimesh.creation.box([0.19, 0.03, 0.03])
    bar.apply_translation([0.08, 0.06, 0.015])
    gc = trained_like_gaussians(cube, 48, seed=0, haze_fraction=0.0)
    gb = trained_like_gaussians(bar, 1500, seed=0, haze_fraction=0.0)
    gb = gb.subset(np.argsort(np.linalg.norm(gb.means - bar.bounds[1], axis=1))[:35])   # the bar's far end
    n = 60                                                                              # a 0.5 m square table
    xy = np.stack(np.meshgrid(np.linspace(-0.25, 0.25, n), np.linspace(-0.25, 0.25, n)), -1).reshape(-1, 2)
    table = Gaussians(np.column_stack([xy, np.zeros(len(xy))]), np.tile([1.0, 0, 0, 0], (len(xy), 1)),
                      np.tile([0.005, 0.005, 0.0005], (len(xy), 1)), np.full(len(xy), 0.95), np.zeros((len(xy), 1, 3)))
    parts = (table, gc, gb)
    g = Gaussians(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("means", "quats", "scales", "opacities")),
                  np.zeros((sum(len(p) for p in parts), 1, 3)))
    ply = g.save_ply(tmp_path / "scene.ply")
    np.save(tmp_path / "labels.npy", np.repeat([0, 1, 2], [len(p) for p in parts]))
    cams = [Camera.from_fov(np.radians(60.0), 160, 120, name=f"{i:03d}",
                            T_world_cam=look_at([0.35 * np.cos(a), 0.35 * np.sin(a), 0.35], [0.0, 0.02, 0.02]))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False))]
    frames = [Frame(image_path=tmp_path / "images" / f"{c.name}.png", camera=c) for c in cams]
    cameras = nerfstudio.write(Dataset(root=tmp_path, frames=frames, has_poses=True), tmp_path / "transforms.json")
    ms = MaskSet()
    for c in cams:
        for label, name, mesh in ((1, "yellow_cube", cube), (2, "toy_hammer", bar)):
            uv = c.project(mesh.vertices)[0]
            hull = uv[ConvexHull(uv).vertices]
            m = np.zeros((c.height, c.width), bool)
            m[polygon(hull[:, 1] - 0.5, hull[:, 0] - 0.5, m.shape)] = True
            ms.add(c.name, label + 10, m, name=name)          # a saved set numbers its objects itself
    ms.save(tmp_path / "masks")
    base = ["geometry", str(ply), "--labels", str(tmp_path / "labels.npy"), "--object", "yellow_cube=1",
            "--object", "toy_hammer=2", "--frame", "ground_truth", "--formats", "", "--cameras", str(cameras)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(base + ["--out", str(tmp_path / "twin"), "--masks", str(tmp_path / "masks")]) == 0
        out = capsys.readouterr().out
        assert main(base + ["--out", str(tmp_path / "plain")]) == 0
    m = Manifest.load(tmp_path / "twin")
    c, h = m.object("yellow_cube"), m.object("toy_hammer")
    assert c.usable and c.problem is None and c.silhouette_coverage >= 0.9 and c.silhouette_precision >= 0.5
    assert (tmp_path / "twin" / c.collision_mesh).is_file()
    assert not h.usable and h.silhouette_coverage < 0.2 and "not whole" in h.problem, h.problem
    assert f"covers {c.silhouette_coverage:.0%} of its masks" in out
    plain = Manifest.load(tmp_path / "plain")
    assert not plain.object("yellow_cube").usable and plain.object("yellow_cube").silhouette_coverage is None
    assert plain.object("yellow_cube").problem == "too few points after cleaning (48 < 50)"
    # masks that name none of the objects, or without the cameras they were drawn in: exit 2
    assert main(base[:-2] + ["--out", str(tmp_path / "x"), "--masks", str(tmp_path / "masks")]) == 2
    assert "--masks needs --cameras" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [-7, 70000])
def test_geometry_cli_labels_out_of_range_name_the_label_file(tmp_path, capsys, bad):
    """found by fuzzing: negative labels were taken silently (a twin written, exit 0; all -7 with --masks: an
    error naming the masks, "no mask names one of the objects"), and a label of 70000 was refused as an object
    'object_70000' naming no file. Now a label outside [0, MAX_LABEL] is an InputError naming the label file,
    as the viewer's reader of a twin's labels says."""
    g, labels, _, _ = synthetic_scene(4000, seed=3)
    ply = g.save_ply(tmp_path / "scene.ply")
    labels = labels.astype(np.int64)
    labels[:5] = bad
    np.save(tmp_path / "labels.npy", labels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["geometry", str(ply), "--labels", str(tmp_path / "labels.npy"), "--out", str(tmp_path / "t"),
                   "--formats", ""])
    err = capsys.readouterr().err
    assert rc == 2 and "labels.npy" in err and "labels must be within [0, 65535]" in err, err[-1000:]
