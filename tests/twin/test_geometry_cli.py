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


def test_geometry_cli_bad_input(tmp_path):
    g, labels, _, _ = synthetic_scene(4000, seed=3)
    ply = g.save_ply(tmp_path / "scene.ply")
    np.save(tmp_path / "short.npy", labels[:10])
    assert main(["geometry", str(tmp_path / "nope.ply"), "--out", str(tmp_path / "t")]) == 2
    assert main(["geometry", str(ply), "--labels", str(tmp_path / "short.npy"), "--out", str(tmp_path / "t")]) == 2
    assert main(["geometry", str(ply), "--object", "bad", "--labels", str(tmp_path / "short.npy"),
                 "--out", str(tmp_path / "t")]) == 2


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
