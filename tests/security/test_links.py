"""Files splattwin wrote into a twin / training / poses folder (records, checkpoints, PLYs, npz) are read only
from inside that folder: a received folder may hold a symbolic link planted to have another file read
(`splat/train.json -> /etc/passwd`). Found by fuzzing: eval, fuse, geometry, train --resume, the viewer and
render read such links, exit 0. Now each is an InputError naming the link (exit 2); links inside the folder
work as before, and a capture folder's links (the one deliberate exception, docs/CONTRACTS.md) are followed."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError


def _link_out(path: Path, elsewhere: Path) -> Path:
    """Move `path` to `elsewhere` and leave a relative symbolic link to it in its place; the link."""
    elsewhere.mkdir(exist_ok=True)
    target = elsewhere / path.name
    path.rename(target)
    os.symlink(os.path.relpath(target, path.parent), path)
    return path


def _link_inside(path: Path) -> Path:
    """Move `path` to a sibling and link it back under its own name (a link that stays in the folder)."""
    kept = path.with_name("kept_" + path.name)
    path.rename(kept)
    os.symlink(kept.name, path)
    return path


def _transforms(path: Path) -> None:
    """A nerfstudio transforms.json of one frame (its image need not exist: read with require_images=False)."""
    path.write_text(json.dumps({"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48,
                                "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}))


def _poses_folder(tmp_path: Path, frame):
    """(poses folder, dataset stand-in): a poses stage's folder with the TwinFrame `frame`, an empty
    poses_report.json and a one-frame transforms.json, and an object with the dataset's `meta` and `root`."""
    poses = tmp_path / "poses"
    poses.mkdir()
    frame.save(poses)
    (poses / "poses_report.json").write_text("{}")
    _transforms(poses / "transforms.json")

    class _Ds:
        meta = {"path": str(poses / "transforms.json")}
        root = poses

    return poses, _Ds


def _training_folder(tmp_path: Path) -> Path:
    from splattwin.splat.gaussians import Gaussians

    d = tmp_path / "splat"
    d.mkdir()
    n = 4
    g = Gaussians(np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.05), np.full(n, 0.5),
                  np.zeros((n, 1, 3)))
    g.save_ply(d / "point_cloud.ply")
    (d / "train.json").write_text(json.dumps({"config": {"rasterize_mode": "antialiased", "eps2d": 0.3}}))
    return d


def test_training_record_linked_out_is_refused_naming_the_link(tmp_path):
    """train.json (eval, fuse, geometry read it beside the splat PLY) through a link out of its folder."""
    from splattwin.splat.config import filter_beside
    from splattwin.splat.eval import resolve_ply

    d = _training_folder(tmp_path)
    assert filter_beside(d / "point_cloud.ply")[0] == "antialiased"
    link = _link_out(d / "train.json", tmp_path / "elsewhere")
    for read in (lambda: filter_beside(d / "point_cloud.ply"), lambda: resolve_ply(d)):
        with pytest.raises(InputError, match="symbolic link .* outside its folder") as e:
            read()
        assert e.value.path == link


def test_splat_ply_linked_out_of_a_training_folder_is_refused(tmp_path):
    from splattwin.splat.eval import resolve_ply

    d = _training_folder(tmp_path)
    link = _link_out(d / "point_cloud.ply", tmp_path / "elsewhere")
    with pytest.raises(InputError, match="outside its folder") as e:
        resolve_ply(d)
    assert e.value.path == link


def test_linked_folder_is_named_and_links_inside_still_work(tmp_path):
    """A link to a folder elsewhere is named (not the file under it); links that stay inside are followed."""
    from splattwin.splat.config import filter_beside
    from splattwin.splat.eval import resolve_ply

    d = _training_folder(tmp_path)
    _link_inside(d / "train.json")
    _link_inside(d / "point_cloud.ply")
    ply, rec = resolve_ply(d)
    assert ply == d / "point_cloud.ply" and rec["config"]["rasterize_mode"] == "antialiased"
    assert filter_beside(ply)[0] == "antialiased"

    twin = tmp_path / "twin"
    twin.mkdir()
    shutil.move(d, tmp_path / "store")
    os.symlink(tmp_path / "store", twin / "splat")
    from splattwin.paths import own_file

    with pytest.raises(InputError) as e:
        own_file(twin, twin / "splat" / "train.json", "train.json")
    assert e.value.path == twin / "splat"


def test_poses_records_linked_out_are_refused(tmp_path):
    """poses/frame.json, poses/poses_report.json and poses/transforms.json (read by eval, fuse, train)."""
    from splattwin.capture import nerfstudio
    from splattwin.poses.twin_frame import TwinFrame, load_frame
    from splattwin.splat.init import poses_report_path

    poses, _Ds = _poses_folder(tmp_path, TwinFrame(source="unscaled", scaled=False))

    assert not load_frame(poses).scaled and poses_report_path(_Ds()) == poses / "poses_report.json"
    elsewhere = tmp_path / "elsewhere"
    for name, read in (("frame.json", lambda: load_frame(poses)),
                       ("poses_report.json", lambda: poses_report_path(_Ds())),
                       ("transforms.json", lambda: nerfstudio.read(poses / "transforms.json", require_images=False))):
        link = _link_out(poses / name, elsewhere)
        with pytest.raises(InputError, match="outside its folder") as e:
            read()
        assert e.value.path == link
        link.unlink()
        (elsewhere / name).rename(poses / name)
        _link_inside(poses / name)   # inside the folder: read as before
        read()


def test_capture_transforms_json_linked_out_is_still_read(tmp_path):
    """The deliberate exception: a user's capture (no poses_report.json beside: splattwin did not write it)
    commonly links into a dataset store, and those links are followed."""
    from splattwin.capture import nerfstudio

    cap = tmp_path / "capture"
    cap.mkdir()
    _transforms(cap / "transforms.json")
    _link_out(cap / "transforms.json", tmp_path / "store")
    assert len(nerfstudio.read(cap / "transforms.json", require_images=False).frames) == 1


@pytest.fixture(scope="module")
def gt_twin(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("links_gt_twin")
    twin_from_scene(scene_small, out)
    return out


def test_robot_results_linked_out_is_refused(gt_twin, tmp_path):
    """robot/results.json (the viewer's and render's staleness check) through a link out of the twin."""
    from splattwin.playback.view_model import TwinView
    from splattwin.robot.outputs import stale_results

    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    (twin / "robot").mkdir(exist_ok=True)
    (twin / "robot" / "results.json").write_text(json.dumps({"twin_digest": "0" * 64}))
    assert "earlier state" in stale_results(twin)
    link = _link_out(twin / "robot" / "results.json", tmp_path / "elsewhere")
    with pytest.raises(InputError, match="outside its folder") as e:
        stale_results(twin)
    assert e.value.path == link
    from splattwin.playback.view_model import _made_on_another_twin

    with pytest.raises(InputError, match="outside its folder"):
        _made_on_another_twin(twin)
    link.unlink()
    assert TwinView.load(twin).manifest.objects


def test_render_names_the_link_of_twin_json_and_rollout(gt_twin, tmp_path, cli):
    """render checked the rollout's twin first: a twin.json linked out said 'rollout is not this twin's';
    a rollout.npz linked out was read. Now each is bad input naming the link."""
    from security_helpers import assert_bad_input

    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    (twin / "robot").mkdir(exist_ok=True)
    (twin / "robot" / "rollout.npz").write_bytes(b"not read")
    elsewhere = tmp_path / "elsewhere"
    _link_out(twin / "robot" / "rollout.npz", elsewhere)
    res = cli("render", twin, "--out", tmp_path / "v.mp4")
    assert_bad_input(res, "rollout.npz", "outside its folder")
    (twin / "robot" / "rollout.npz").unlink()
    (twin / "robot" / "rollout.npz").write_bytes(b"not read")
    _link_out(twin / "twin.json", elsewhere)
    res = cli("render", twin, "--out", tmp_path / "v.mp4")
    assert_bad_input(res, "twin.json", "leads outside")
    assert "not this twin" not in res.err


def test_readers_that_warn_on_a_bad_file_still_refuse_a_link_out(tmp_path):
    """eval's units (frame.json) and geometry's optional cameras (--cameras) only warn on a bad file; a link
    out of the poses folder read nothing and exited 0 with that warning. Now it is bad input naming the link."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.splat.eval import dataset_units
    from splattwin.twin.build import _capture

    poses, _Ds = _poses_folder(tmp_path, TwinFrame(source="marker", scaled=True))

    assert dataset_units(_Ds()) == "m"
    (poses / "frame.json").write_text("[")   # a bad file: a warning, as before
    assert dataset_units(_Ds()) != "m"
    link = _link_out(poses / "frame.json", tmp_path / "elsewhere")
    with pytest.raises(InputError, match="outside its folder") as e:
        dataset_units(_Ds())
    assert e.value.path == link
    link = _link_out(poses / "transforms.json", tmp_path / "elsewhere")
    with pytest.raises(InputError, match="outside its folder") as e:
        _capture(tmp_path / "out", poses / "transforms.json")
    assert e.value.path == link
