"""Every bad input of the issue exits 2 naming the file and the problem, internal errors exit 1, and no
traceback reaches the user without --debug. Hypothesis mutates valid transforms.json, twin.json and
COCO files: whatever it writes, loading either works or raises InputError naming the file."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from splattwin import io
from splattwin.errors import InputError

from security_helpers import assert_bad_input

FUZZ = settings(max_examples=120, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

# values of every JSON type, including the ones readers do not expect
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.floats(allow_nan=False),
              st.text(max_size=12), st.sampled_from(["../x", "/etc/passwd", "images/train_000.png", "nan"])),
    lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12)


@st.composite
def mutations(draw, doc):
    """A copy of `doc` with one to three values somewhere inside replaced, deleted or added."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 3))):
        node, path = doc, []
        while isinstance(node, (dict, list)) and node and draw(st.booleans()):
            key = draw(st.sampled_from(sorted(node) if isinstance(node, dict) else list(range(len(node)))))
            path.append((node, key))
            node = node[key]
        if not path:
            return draw(json_values)
        parent, key = path[-1]
        action = draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "delete" and isinstance(parent, dict):
            del parent[key]
        elif action == "add" and isinstance(parent, dict):
            parent[draw(st.text(max_size=6))] = draw(json_values)
        else:
            parent[key] = draw(json_values)
    return doc


# -- the list ----------------------------------------------------------------------------------
@pytest.mark.parametrize("frames,needle", [
    ([{"file_path": None}], "file_path"),
    (["not an object"], "frame 0"),
    ([{"file_path": "images/train_000.png", "transform_matrix": [["a"] * 4] * 4}], "transform_matrix"),
    ([{"file_path": "images/train_000.png", "transform_matrix": "eye"}], "transform_matrix"),
    ([{"file_path": "images/train_000.png", "transform_matrix": np.eye(4).tolist(), "fl_x": "wide"}], "intrinsics"),
    ([{"file_path": "images/train_000.png", "transform_matrix": np.eye(4).tolist(), "w": 10**6, "h": 10**6}],
     "megapixels"),
])
def test_malformed_transforms_json(tiny_dataset, tmp_path, cli, frames, needle):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    meta = json.loads((ds / "transforms.json").read_text())
    meta["frames"] = frames
    (ds / "transforms.json").write_text(json.dumps(meta))
    assert_bad_input(cli("capture", "info", ds), "transforms.json", needle)


@pytest.fixture(scope="module")
def gt_twin(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_twin_bad") / "twin"
    twin_from_scene(scene_small, out)
    return out


@pytest.mark.parametrize("case", ["non_mesh", "json_as_mesh", "text_pose", "nan_pose", "bad_extent", "huge_table",
                                  "flat_table"])
def test_malformed_twin(gt_twin, tmp_path, cli, case):
    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    d = json.loads((twin / "twin.json").read_text())
    o = d["objects"][0]
    needles = ["twin.json"]
    if case == "non_mesh":
        (twin / o["convex_parts"][0]).write_text("this is not a mesh\n")
        needles = [Path(o["convex_parts"][0]).name]
    elif case == "json_as_mesh":
        o["convex_parts"] = ["twin.json"]
        needles = ["twin.json", "must be one of"]
    elif case == "text_pose":
        o["T_world_obj"] = "identity"
        needles += ["T_world_obj"]
    elif case == "nan_pose":
        o["T_world_obj"][0][3] = float("nan")
        needles += ["T_world_obj"]
    elif case == "huge_table":  # was exported as an MJCF MuJoCo cannot load (size="1e+300 ..."), exit 0
        d["background"]["table_extent"] = [-1e300, 1e300, -1e300, 1e300]
        needles += ["table_extent"]
    elif case == "flat_table":  # a zero MJCF box size
        d["background"]["table_thickness"] = 0.0
        needles += ["table_thickness"]
    else:
        o["bbox_extent"] = [0.1, -1, 0.1]
        needles += ["bbox_extent"]
    (twin / "twin.json").write_text(json.dumps(d))
    assert_bad_input(cli("export", twin, "--formats", "mjcf,urdf,moveit,gltf"), *needles)
    assert_bad_input(cli("plan", twin, "--no-render"), needles[0])
    res = cli("report", twin)
    if case in ("non_mesh", "json_as_mesh"):  # this twin has no cameras: the report draws no meshes
        assert res.rc in (0, 2) and "Traceback" not in res.err
    else:
        assert_bad_input(res, needles[0])


def test_out_pointing_at_a_file(tmp_path, cli, tiny_dataset):
    f = tmp_path / "a_file"
    f.write_text("x")
    from splattwin.scene.synthetic import synthetic_scene

    g, _, _, _ = synthetic_scene(500, seed=0)
    ply = g.save_ply(tmp_path / "s.ply")
    assert_bad_input(cli("build", tiny_dataset, "--out", f, "--iters", "5"), "a_file", "not a folder")
    assert_bad_input(cli("geometry", ply, "--out", f), "a_file", "not a folder")
    assert_bad_input(cli("train", tiny_dataset, f, "--iters", "5", "--no-progress"), "a_file", "not a folder")
    assert_bad_input(cli("build", tiny_dataset, "--out", f / "sub", "--iters", "5"), "a_file/sub", "cannot be created")
    assert f.read_text() == "x"


def test_mask_errors_name_the_mask_file_and_come_before_training(tiny_dataset, tmp_path, cli):
    """Inside build, a wrong-size mask names that mask file (not another object's), and is found in
    the preflight: no pose estimation or training has run."""
    masks = tmp_path / "masks"
    ok = np.zeros((36, 48), np.uint8)
    ok[5:15, 5:15] = 255
    io.write_image(masks / "train_000" / "aaa.png", ok)
    io.write_image(masks / "train_000" / "zzz.png", np.zeros((30, 40), np.uint8))   # the wrong one
    out = tmp_path / "twin"
    res = cli("build", tiny_dataset, "--masks", masks, "--out", out, "--iters", "5")
    assert_bad_input(res, "zzz.png", "40x30", "48x36")
    assert not (out / "poses").exists() and not (out / "splat").exists()
    io.write_image(masks / "train_000" / "zzz.png", np.zeros((36, 48), np.uint8))  # right size, empty
    res = cli("build", tiny_dataset, "--masks", masks, "--out", out, "--iters", "5")
    assert_bad_input(res, "masks", "'zzz'", "seen in no view")


def test_coco_rle_errors_name_the_file(tmp_path):
    from splattwin.semantics.masks import load_masks

    coco = io.write_json(tmp_path / "ann.json", {
        "images": [{"id": 1, "file_name": "a.png", "height": 4, "width": 4}],
        "categories": [{"id": 1, "name": "box"}],
        "annotations": [{"image_id": 1, "category_id": 1, "segmentation": {"size": [4, 4], "counts": "\x7f\x7f"}}]})
    with pytest.raises(InputError, match="annotation 0") as e:
        load_masks(coco)
    assert e.value.path == coco


def test_nan_object_pose_message(scene_small):
    from splattwin.robot.task import load_task, validate_task
    from splattwin.twin.manifest import Manifest

    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import ObjectEntry

    T = np.eye(4)
    T[0, 3] = np.nan
    man = Manifest(frame=TwinFrame("ground_truth", True), objects=[ObjectEntry("blue_box", 1, T_world_obj=T.tolist()),
                                                                 ObjectEntry("cardboard_box", 2),
                                                                 ObjectEntry("yellow_cube", 3),
                                                                 ObjectEntry("toy_hammer", 4)],
                   config={"target_frame": {"center": [0.1, 0.1, 0.0], "size": 0.2}})
    T_base = np.eye(4)
    T_base[0, 3] = -0.5
    with pytest.raises(InputError, match="not finite") as e:
        validate_task(load_task(None, man), man, scene_small, T_base)
    assert "nan m" not in str(e.value)


def test_internal_errors_exit_1_without_traceback(gt_twin, cli, monkeypatch):
    import splattwin.report.build as rb

    def broken(*a, **k):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(rb, "build_report", broken)
    res = cli("report", gt_twin)
    assert res.rc == 1 and "Traceback" not in res.err
    assert "internal error: RuntimeError: simulated bug" in res.err and "--debug" in res.err
    res = cli("report", gt_twin, "--debug")
    assert res.rc == 1 and "Traceback" in res.err and "simulated bug" in res.err


# -- fuzzing -----------------------------------------------------------------------------------------
def _fuzz_file(src: Path, tmp_path: Path, name: str, load_and_check) -> None:
    """Copy folder `src`, then for many mutations of its JSON file `name` write the mutant and call
    `load_and_check(folder)` (which must not raise anything but the asserted errors)."""
    folder = tmp_path / "fuzzed"
    shutil.copytree(src, folder)
    good = json.loads((src / name).read_text())

    @FUZZ
    @given(doc=mutations(good))
    def check(doc):
        (folder / name).write_text(json.dumps(doc))
        load_and_check(folder)
    check()


def test_fuzzed_transforms_json(tiny_dataset, tmp_path):
    from splattwin.capture import load_dataset

    def load(ds):
        try:
            load_dataset(ds)
        except InputError as e:
            assert e.path is not None
    _fuzz_file(tiny_dataset, tmp_path, "transforms.json", load)


def test_fuzzed_twin_json(gt_twin, tmp_path):
    from splattwin.twin.manifest import Manifest

    def load(twin):
        try:
            m = Manifest.load(twin)
        except InputError as e:
            assert e.path == twin / "twin.json"
            return
        for _, rel in m.paths():   # whatever loads is confined and well-typed
            assert (twin / rel).resolve().is_relative_to(twin.resolve())
        for o in m.objects:
            assert o.pose.shape == (4, 4) and np.all(np.isfinite(o.pose))
    _fuzz_file(gt_twin, tmp_path, "twin.json", load)


def test_fuzzed_coco(tmp_path):
    from splattwin.semantics.masks import load_masks

    good = {"images": [{"id": 1, "file_name": "a.png", "height": 6, "width": 5}],
            "categories": [{"id": 1, "name": "box"}, {"id": 2, "name": "toy hammer"}],
            "annotations": [{"image_id": 1, "category_id": 1, "segmentation": {"size": [6, 5], "counts": [3, 20, 7]}},
                            {"image_id": 1, "category_id": 2, "segmentation": [[0, 0, 4, 0, 4, 4]]}]}
    path = tmp_path / "ann.json"

    @FUZZ
    @given(doc=mutations(good))
    def check(doc):
        path.write_text(json.dumps(doc))
        try:
            ms = load_masks(path)
        except InputError as e:
            assert e.path == path
            return
        for view in ms.masks:
            assert "/" not in view and view not in (".", "..")
    check()
