"""What a robot engineer relies on in the exports (audit 5a): an unusable object stays an obstacle (H4), a
floating object is flagged (M2), object names never clash with the exports' own names (M3), one export
ID everywhere and ROS-usable mesh URIs (M4), twin.json describes every file (L1), unit comments (L2),
relative MJCF paths for any folder name (L3), mass estimates flagged (L5), glTF obstacles (L6), MoveIt
frame named `twin` (H3)."""

from __future__ import annotations

import json
import logging
import shutil
import warnings
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest
import trimesh
import yaml

from splattwin.cli import main
from splattwin.errors import InputError
from splattwin.names import check_unique, export_id, object_name
from splattwin.poses.twin_frame import TwinFrame
from splattwin.scene.synthetic import synthetic_scene
from splattwin.twin.build import build_twin
from splattwin.twin.manifest import Manifest
from splattwin.twin.moveit import parse_scene

LIFT = 0.06   # m: the box's splats are lifted this far (beyond foot_gap 0.05): nothing fills it down


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A metric twin where the cube keeps 30 splats (unusable: < 50), the box floats 6 cm above the table,
    and `ghost` has no splats at all; all exports written. (twin folder, manifest, cube's kept points, log)"""
    g, labels, objects, _ = synthetic_scene(16000, seed=1, obstacle=True)
    cube = np.flatnonzero((labels == 2) & (g.opacities > 0.5))
    keep = np.ones(len(g), bool)
    keep[labels == 2] = False
    keep[cube[:: max(1, len(cube) // 30)][:30]] = True
    g, labels = g.subset(np.flatnonzero(keep)), labels[keep]
    g.means[labels == 1] += [0.0, 0.0, LIFT]
    out = tmp_path_factory.mktemp("safety") / "twin"
    handler = _ListHandler()
    logging.getLogger("splattwin").addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = build_twin(g, labels, objects + [("ghost", 9, "a ghost")], out, TwinFrame("ground_truth", scaled=True),
                           progress=False)
    finally:
        logging.getLogger("splattwin").removeHandler(handler)
    return out, m, g.means[labels == 2], handler.lines


class _ListHandler(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record):
        self.lines.append(record.getMessage())


# -- H4: an unusable object is a static obstacle in every collision export ------------------------------
def test_unusable_object_keeps_its_obstacle_box_in_twin_json(built):
    out, m, cube_pts, log = built
    c = Manifest.load(out).object("cube")
    assert not c.usable and c.obstacle_only and "too few points" in c.problem
    lo = c.pose[:3, 3] - np.asarray(c.bbox_extent) / 2
    hi = c.pose[:3, 3] + np.asarray(c.bbox_extent) / 2
    gt_lo, gt_hi = np.array([0.169, -0.181, 0.0]), np.array([0.231, -0.119, 0.05])   # the synthetic cube
    assert np.all(lo <= gt_lo + 0.002) and np.all(hi >= gt_hi - 0.002)      # covers the real cube
    assert np.all(hi - lo < (gt_hi - gt_lo) + 0.03), c.bbox_extent        # not its stray splat at 12 cm
    assert lo[2] == pytest.approx(m.background.table_height, abs=1e-6)      # reaches down to the table
    assert any("'cube' is unusable" in s and "static obstacle" in s for s in log)
    ghost = m.object("ghost")
    assert not ghost.obstacle_only and "no geometry at all" in ghost.problem
    assert any("'ghost'" in s and "no geometry at all" in s for s in log)


def test_unusable_object_is_in_mjcf_urdf_moveit_gltf(built):
    import mujoco
    import yourdfpy

    out, m, *_ = built
    c = m.object("cube")
    model = mujoco.MjModel.from_xml_path(str(out / "export" / "scene.xml"))
    b = model.body("cube")
    assert model.body_jntnum[b.id] == 0                                      # static: no free joint
    gid = model.geom("cube/obstacle").id
    assert np.allclose(model.geom_size[gid], np.asarray(c.bbox_extent) / 2)
    assert np.allclose(model.body_pos[b.id], c.pose[:3, 3])
    assert "ghost" not in (out / "export" / "scene.xml").read_text()
    u = yourdfpy.URDF.load(str(out / "export" / "scene.urdf"))
    assert np.allclose(u.get_transform("cube", "world"), c.pose, atol=1e-6)
    assert np.allclose(u.link_map["cube"].collisions[0].geometry.box.size, c.bbox_extent)
    _, objs = parse_scene((out / "export" / "moveit" / "scene.scene").read_text())
    cube = {o.id: o for o in objs}["cube"]
    assert cube.shapes[0].kind == "box" and np.allclose(cube.T_world_obj, c.pose, atol=1e-6)
    msgs = yaml.safe_load((out / "export" / "moveit" / "collision_objects_boxes.yaml").read_text())
    assert np.allclose({x["id"]: x for x in msgs}["cube"]["primitives"][0]["dimensions"], c.bbox_extent)
    glb = trimesh.load(out / "export" / "scene.glb")
    assert "cube" in glb.graph.nodes and "background_obstacles" in glb.graph.nodes   # L6 too


def test_robot_world_collides_with_the_obstacle_but_does_not_free_it(built):
    from splattwin.robot.world import build_world

    out, m, *_ = built
    w = build_world(out, visual=False)
    assert "cube" not in w.objects and {"box", "hammer"} <= set(w.objects)
    b = w.model.body("cube").id
    assert w.model.body_jntnum[b] == 0 and w.model.body_geomnum[b] == 1


def test_obstacle_box_pads_trims_and_reaches_the_table():
    from splattwin.geometry.convert import ObjectGeometry, obstacle_box
    from splattwin.geometry.options import GeometryOptions

    opts = GeometryOptions()
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0, 0.02], [0.03, 0.03, 0.05], (200, 3))
    far = np.array([[1.0, 1.0, 0.5]])                              # one stray floater
    r = ObjectGeometry("x", 1, usable=False)
    obstacle_box(r, np.concatenate([pts, far]), opts, support_z=0.0)
    lo, hi = r.T_world_obj[:3, 3] - r.extent / 2, r.T_world_obj[:3, 3] + r.extent / 2
    assert r.obstacle and hi[0] < 0.1                              # the floater does not make a wall
    assert lo[2] == 0.0 and hi[2] == pytest.approx(0.05 + opts.obstacle_pad, abs=2e-3)
    r2 = ObjectGeometry("y", 2, usable=False)
    obstacle_box(r2, np.zeros((0, 3)), opts, support_z=0.0)
    assert not r2.obstacle


def test_obstacle_box_bounds_a_small_cube_from_its_few_splats_with_margin():
    """audit 7B D8: a 2.5 cm cube with 3 labelled splats got a 2.0 cm box (their centres, point-like, grown
    by 1 cm): a keep-out volume smaller than the object. The box now holds each splat's half-opaque extent
    and then the pad, so it bounds the cube on every side."""
    from splattwin.geometry.convert import ObjectGeometry, obstacle_box, splat_half_extents
    from splattwin.geometry.options import GeometryOptions
    from splattwin.splat.gaussians import Gaussians, rgb_to_sh0

    opts = GeometryOptions().resolved(scene_scale=1.0)
    lo_c, hi_c = np.array([0.2, 0.3, 0.0]), np.array([0.225, 0.325, 0.025])   # the cube on the table z = 0
    # trained surface splats: flat discs 1-2 mm inside the face they render (top, -x side, -y side)
    means = np.array([[0.2125, 0.3125, 0.023], [0.2015, 0.3125, 0.0125], [0.2125, 0.3015, 0.0125]])
    scales = np.array([[0.008, 0.008, 0.001], [0.001, 0.008, 0.008], [0.008, 0.001, 0.008]])
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (3, 1)), scales=scales, opacities=np.full(3, 0.95),
                  sh=rgb_to_sh0(np.full((3, 3), 0.8))[:, None, :])
    r = ObjectGeometry("yellow_cube", 3, usable=False)
    obstacle_box(r, g.means, opts, support_z=0.0, half_extent=splat_half_extents(g, np.arange(3), opts))
    lo, hi = r.T_world_obj[:3, 3] - r.extent / 2, r.T_world_obj[:3, 3] + r.extent / 2
    assert np.all(lo[:2] <= lo_c[:2] - 0.005) and np.all(hi <= hi_c + 0.03), (lo, hi)   # margin, not a wall
    assert np.all(hi >= hi_c + 0.005) and lo[2] == 0.0, (lo, hi)
    assert np.all(r.extent[:2] >= 0.025 + 0.01) and r.extent[2] >= 0.025 + 0.005   # the table is its bottom


def test_obstacle_box_keeps_a_thin_extremity_and_drops_a_floater():
    """The 2 % trimmed per side and axis cut a real extremity (a handle's last 4 of 200 points, 1.2 cm,
    beyond the 1 cm pad); a stray floater is still left out (a group of its own)."""
    from splattwin.geometry.convert import ObjectGeometry, obstacle_box
    from splattwin.geometry.options import GeometryOptions

    opts = GeometryOptions()
    rng = np.random.default_rng(1)
    head = rng.uniform([0, 0, 0.0], [0.03, 0.03, 0.03], (180, 3))
    handle = np.c_[np.linspace(0.033, 0.09, 20), np.full(20, 0.015), np.full(20, 0.015)]   # 3 mm apart
    far = np.array([[1.0, 1.0, 0.5]])
    r = ObjectGeometry("toy_hammer", 4, usable=False)
    obstacle_box(r, np.concatenate([head, handle, far]), opts, support_z=0.0)
    hi = r.T_world_obj[:3, 3] + r.extent / 2
    assert hi[0] == pytest.approx(0.09 + opts.obstacle_pad) and hi[1] < 0.1 and hi[2] < 0.1


# -- M2: a floating object is flagged -----------------------------------------------------------------
def test_floating_object_gets_a_problem_the_others_do_not(built):
    out, m, *_ = built
    box = Manifest.load(out).object("box")
    assert box.usable and "floating" in (box.problem or ""), box.problem
    assert m.object("hammer").problem is None


def test_object_standing_on_another_is_not_floating():
    from splattwin.geometry.convert import ObjectGeometry, flag_floating
    from splattwin.geometry.options import GeometryOptions

    def obj(name, z, size=0.05):
        T = np.eye(4)
        T[2, 3] = z + size / 2
        return ObjectGeometry(name, 1, collision=trimesh.creation.box(extents=[size] * 3), T_world_obj=T,
                              extent=np.full(3, size))

    low, top, air = obj("low", 0.0, 0.08), obj("top", 0.08), obj("air", 0.03)
    air.T_world_obj[0, 3] = 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flag_floating([low, top, air], 0.0, GeometryOptions())
    assert low.problem is None and top.problem is None
    assert "floating" in air.problem and "0.03 m above the table top" in air.problem


# -- M3: reserved names --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["table", "world", "World", "floor", "background", "background_obstacles",
                                  "twin_z_up", "twin-z-up", "twin"])
def test_reserved_names_are_refused(name):
    with pytest.raises(InputError, match="reserved"):
        object_name(name, "objects.json")
    assert object_name("table 1") == "table 1" and object_name("world map") == "world map"


@pytest.mark.parametrize("name", ["table", "world"])
def test_twin_json_with_a_reserved_name_is_refused_by_export(built, tmp_path, capsys, name):
    out, *_ = built
    t = tmp_path / "t"
    shutil.copytree(out, t)
    d = json.loads((t / "twin.json").read_text())
    d["objects"][0]["name"] = name
    d["objects"][0].pop("export_id", None)
    (t / "twin.json").write_text(json.dumps(d))
    assert main(["export", str(t)]) == 2
    err = capsys.readouterr().err
    assert "reserved" in err and "twin.json" in err and repr(name) in err


# -- M4: one export ID, URDF mesh URIs -----------------------------------------------------------------
def test_export_id_and_uniqueness():
    assert export_id("toy hammer") == "toy_hammer" and export_id("a-b.c") == "a_b_c"
    assert export_id("3d box") == "obj_3d_box"
    with pytest.raises(InputError, match="export ID"):
        check_unique(["a-b", "a_b"])


def _renamed(out: Path, tmp: Path, old: str, new: str) -> Path:
    t = tmp / "renamed twin"
    shutil.copytree(out, t)
    d = json.loads((t / "twin.json").read_text())
    for o in d["objects"]:
        if o["name"] == old:
            o["name"], o["export_id"] = new, export_id(new)
    (t / "twin.json").write_text(json.dumps(d))
    return t


def test_one_export_id_in_every_export(built, tmp_path):
    import mujoco

    out, *_ = built
    t = _renamed(out, tmp_path, "hammer", "toy hammer")
    assert main(["export", str(t)]) == 0
    ex = t / "export"
    model = mujoco.MjModel.from_xml_path(str(ex / "scene.xml"))
    assert model.body("toy_hammer").id > 0
    urdf = (ex / "scene.urdf").read_text()
    assert 'link name="toy_hammer"' in urdf and "toy hammer" not in urdf.split("-->")[-1].replace(
        "objects/toy hammer", "")  # the human name only in mesh folders
    assert (ex / "toy_hammer.urdf").is_file() and not (ex / "toy hammer.urdf").exists()
    _, objs = parse_scene((ex / "moveit" / "scene.scene").read_text())
    assert "toy_hammer" in {o.id for o in objs}
    assert "toy_hammer" in trimesh.load(ex / "scene.glb").graph.nodes
    man = Manifest.load(t)
    assert man.object("toy hammer").export_id == "toy_hammer"


@pytest.mark.parametrize("uri", ["file", "package://my_twin"])
def test_urdf_mesh_uris(built, tmp_path, uri):
    out, *_ = built
    t = _renamed(out, tmp_path, "hammer", "toy hammer")
    assert main(["export", str(t), "--formats", "urdf", "--urdf-uri", uri]) == 0
    text = (t / "export" / "scene.urdf").read_text()
    names = [s.split('"')[1] for s in text.split("filename=")[1:]]
    assert names and all(" " not in n for n in names)                # URIs: spaces percent-encoded
    if uri == "file":
        assert all(n.startswith("file:///") and Path(unquote(urlparse(n).path)).is_file() for n in names)
    else:
        assert all(n.startswith("package://my_twin/") and (t / unquote(n[len("package://my_twin/"):])).is_file()
                   for n in names)
    assert any(e.get("mesh_paths") == uri for e in Manifest.load(t).export_files)


@pytest.mark.parametrize("uri", ["file", "package://my_twin"])
def test_percent_encoded_urdf_uris_are_announced(built, tmp_path, uri, caplog):
    """A space in the twin's path (file://) or an object's folder (package://) is percent-encoded (RFC 8089,
    what ROS resource_retriever decodes); yourdfpy opens the path as written and misses such a mesh, MuJoCo
    reads no file:// URI. The export warns once, naming the characters and the way out (relative filenames),
    and each URDF says so in a comment; the default relative filenames load in yourdfpy as they are."""
    import yourdfpy

    out, *_ = built
    t = _renamed(out, tmp_path, "hammer", "toy hammer")          # "renamed twin": a space in the twin path
    if uri != "file":
        shutil.move(t / "objects" / "hammer", t / "objects" / "toy hammer")   # and in an object's folder
        d = json.loads((t / "twin.json").read_text())
        for o in d["objects"]:
            for k in ("visual_mesh", "collision_mesh", "splat_ply"):
                if isinstance(o.get(k), str):
                    o[k] = o[k].replace("objects/hammer/", "objects/toy hammer/")
            if o.get("convex_parts"):
                o["convex_parts"] = [p.replace("objects/hammer/", "objects/toy hammer/") for p in o["convex_parts"]]
        (t / "twin.json").write_text(json.dumps(d))
    with caplog.at_level("WARNING", logger="splattwin"):
        assert main(["export", str(t), "--formats", "urdf", "--urdf-uri", uri]) == 0
    warned = [r for r in caplog.records if "percent-encode" in r.getMessage()]
    assert len(warned) == 1 and "space" in warned[0].getMessage() and "--urdf-uri relative" in warned[0].getMessage()
    for f in (t / "export").glob("*.urdf"):
        text = f.read_text()
        assert "%20" in text and "percent-encode" in text.split("<robot")[0], f   # the comment, before <robot>

    def found(urdf):   # meshes yourdfpy loads (it drops a mesh it cannot open, silently)
        u = yourdfpy.URDF.load(str(urdf), load_collision_meshes=True, build_collision_scene_graph=True)
        return len(u.collision_scene.geometry) + len(u.scene.geometry)

    encoded = found(t / "export" / "scene.urdf")
    # the same twin with relative filenames: no warning, and yourdfpy finds every mesh
    caplog.clear()
    with caplog.at_level("WARNING", logger="splattwin"):
        assert main(["export", str(t), "--formats", "urdf"]) == 0
    assert not [r for r in caplog.records if "percent-encode" in r.getMessage()]
    text = (t / "export" / "scene.urdf").read_text()
    assert "percent-encode" not in text
    assert found(t / "export" / "scene.urdf") >= text.count("<mesh filename=") > 0
    assert encoded < found(t / "export" / "scene.urdf")     # what the warning is about


def test_plain_paths_get_no_percent_encoding_note(built, tmp_path, caplog):
    out, *_ = built
    t = tmp_path / "plain_twin"
    shutil.copytree(out, t)
    with caplog.at_level("WARNING", logger="splattwin"):
        assert main(["export", str(t), "--formats", "urdf", "--urdf-uri", "file"]) == 0
    assert not [r for r in caplog.records if "percent-encode" in r.getMessage()]
    assert "%" not in (t / "export" / "scene.urdf").read_text()


def test_bad_urdf_uri_is_refused(built, capsys):
    out, *_ = built
    assert main(["export", str(out), "--urdf-uri", "http://x"]) == 2
    assert "urdf_uri" in capsys.readouterr().err


# -- L3: MJCF paths stay relative whatever the folder is called ----------------------------------------
def test_mjcf_paths_relative_for_xml_special_folder_names(built, tmp_path):
    import mujoco

    out, *_ = built
    t = tmp_path / "a&b'c\"d<e" / "twin"
    shutil.copytree(out, t)
    assert main(["export", str(t), "--formats", "mjcf"]) == 0
    xml = (t / "export" / "scene.xml").read_text()
    files = [s.split('"')[1] for s in xml.split(' file=')[1:]]
    assert files and all(f.startswith("../") for f in files), files[:3]
    mujoco.MjModel.from_xml_path(str(t / "export" / "scene.xml"))


# -- L1, L2, L5, H3 ------------------------------------------------------------------------------------
def test_twin_json_describes_every_export_file(built):
    out, *_ = built
    m = Manifest.load(out)
    listed = {e["path"]: e for e in m.export_files}
    on_disk = {p.relative_to(out).as_posix() for p in (out / "export").rglob("*") if p.is_file()}
    assert on_disk <= set(listed)
    assert all(e["units"] == "m" and e["scaled"] is True and e["frame"] for e in listed.values())
    assert listed["export/scene.xml"]["quaternion"] == "wxyz"
    assert listed["export/moveit/collision_objects.yaml"]["quaternion"] == "xyzw"
    assert "twin_z_up" in listed["export/scene.glb"]["frame"]
    assert listed[m.object("box").splat_ply]["frame"].startswith("object frame")
    # the convex-part OBJs the MJCF and URDF load are listed too (audit 7B D6: they were not)
    import os
    import re

    loaded = {os.path.normpath(os.path.join("export", f)) for f in
              re.findall(r'file="([^"]+\.obj)"', (out / "export" / "scene.xml").read_text())}
    parts = {p.relative_to(out).as_posix() for p in out.rglob("parts/*.obj")}
    assert parts and loaded and loaded <= set(listed) and parts <= set(listed)
    # background part 0 is the table box, which every export writes as a box primitive (audit 10d G5)
    table_part = m.background.convex_parts[0]
    assert table_part not in loaded and listed[table_part]["role"].startswith("the table box")
    assert all(listed[p].get("role", "").startswith("convex collision part") for p in parts - {table_part})


def test_splat_plys_and_objs_state_their_units(built, tmp_path):
    from splattwin.splat.gaussians import Gaussians

    out, m, *_ = built
    box = m.object("box")
    for rel in (box.splat_ply, m.splats):
        header = (out / rel).read_bytes()[:2000].split(b"end_header")[0].decode()
        assert "comment splattwin twin file; units: metres" in header
        assert len(Gaussians.load_ply(out / rel)) > 0                     # our reader skips them
        assert len(trimesh.load(out / rel).vertices) > 0                   # and so does a standard one
    assert (out / box.visual_mesh).read_text().startswith("# splattwin twin file; units: metres")
    assert (out / box.convex_parts[0]).read_text().startswith("# splattwin twin file; units: metres")


def test_unscaled_files_say_unscaled(tmp_path):
    from splattwin.splat.ply import write_gaussians_ply

    g, *_ = synthetic_scene(2000, seed=0)
    p = write_gaussians_ply(tmp_path / "x.ply", g, ["units: UNSCALED\ttwin\nsecond"])
    assert b"comment units: UNSCALED twin second\n" in p.read_bytes()[:500]


def test_masses_are_flagged_as_estimates(built):
    out, m, *_ = built
    assert "uniform density 500 kg/m^3" in m.object("box").mass_source
    assert "masses and inertias: estimate" in (out / "export" / "scene.urdf").read_text()
    assert "masses and inertias: estimate" in (out / "export" / "scene.xml").read_text()


def test_moveit_files_name_the_twin_frame(built):
    out, *_ = built
    text = (out / "export" / "moveit" / "collision_objects.yaml").read_text()
    assert text.startswith("# frame_id twin:")
    assert {x["header"]["frame_id"] for x in yaml.safe_load(text)} == {"twin"}


def test_the_pipelines_own_splat_ply_is_not_rewritten(tmp_path):
    """The splats stage recorded splat/point_cloud.ply's digest: new bytes (the unit comment) would make
    every later build train again."""
    from splattwin.splat.gaussians import Gaussians

    g, labels, objects, _ = synthetic_scene(6000, seed=2)
    out = tmp_path / "twin"
    ply = g.save_ply(out / "splat" / "point_cloud.ply")
    before = ply.read_bytes()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(Gaussians.load_ply(ply), labels, objects, out, TwinFrame("ground_truth", scaled=True),
                   formats=(), progress=False, splats_path=ply)
    assert ply.read_bytes() == before


def test_gltf_obstacle_box_is_translucent(built):
    """A vertex colour's alpha is ignored under glTF's default material (OPAQUE): the obstacle box needs a
    material with alphaMode BLEND (audit 6b D10). Read from the GLB's JSON chunk, as any viewer reads it."""
    import struct

    out, *_ = built
    data = (out / "export" / "scene.glb").read_bytes()
    n = struct.unpack("<I", data[12:16])[0]
    js = json.loads(data[20:20 + n])
    mesh_of = {nd["name"]: nd.get("mesh") for nd in js["nodes"]}
    prims = js["meshes"][mesh_of["cube"]]["primitives"]
    mat = js["materials"][prims[0]["material"]]
    assert mat["alphaMode"] == "BLEND"
    assert mat["pbrMetallicRoughness"]["baseColorFactor"][3] == pytest.approx(0.5, abs=0.01)
    # red, as the viewer draws it: baseColorFactor is linear (glTF 3.9.2), the viewer's colour sRGB (audit 10d G1)
    from splattwin.twin.gltf import OBSTACLE_RGBA, linear_from_srgb
    assert np.allclose(mat["pbrMetallicRoughness"]["baseColorFactor"][:3],
                       linear_from_srgb(OBSTACLE_RGBA)[:3] / 255.0, atol=1e-6)
    box = js["meshes"][mesh_of["box"]]["primitives"][0]                        # a real mesh stays opaque
    assert "material" not in box or js["materials"][box["material"]].get("alphaMode", "OPAQUE") == "OPAQUE"
    glb = trimesh.load(out / "export" / "scene.glb")
    assert glb.geometry["cube"].visual.material.alphaMode == "BLEND"


def _older(built, tmp_path: Path) -> Path:
    """The twin as an older build wrote it: no obstacle_only (nor export_id, mass_source) per object."""
    out = tmp_path / "old"
    shutil.copytree(built[0], out)
    d = json.loads((out / "twin.json").read_text())
    for o in d["objects"]:
        for k in ("obstacle_only", "export_id", "mass_source"):
            o.pop(k, None)
    d.pop("export_files", None)
    (out / "twin.json").write_text(json.dumps(d))
    return out


def test_export_of_an_older_twin_warns_once_that_its_unusable_object_has_no_box(built, tmp_path, caplog):
    """audit 6b D8: an older twin.json's unusable object (no obstacle_only) was left out of every collision
    export silently. `export` names it and how to give it its box; a new twin (ghost: no splats, no box on
    purpose) gets no such warning."""
    old = _older(built, tmp_path)
    with caplog.at_level(logging.WARNING, logger="splattwin"):
        assert main(["export", str(old), "--formats", "mjcf"]) == 0
    said = [r.getMessage() for r in caplog.records if "predates obstacle-only boxes" in r.getMessage()]
    assert len(said) == 1, said
    assert "'cube' is unusable and in no collision export" in said[0] and "--from twin" in said[0]
    assert "ghost" not in said[0]
    assert "cube" not in (old / "export" / "scene.xml").read_text()   # still left out: a warning, not a fix
    # export rewrote twin.json (obstacle_only: false now written): the next command still warns
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splattwin"):
        assert main(["export", str(old), "--formats", "mjcf"]) == 0
    assert sum("predates obstacle-only boxes" in r.getMessage() for r in caplog.records) == 1
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splattwin"):
        assert main(["export", str(built[0]), "--formats", "mjcf"]) == 0
    assert not any("predates" in r.getMessage() for r in caplog.records)


def test_plan_on_an_older_twin_warns_that_its_unusable_object_is_not_in_the_robots_world(built, tmp_path, caplog):
    old = _older(built, tmp_path)
    task = tmp_path / "task.yaml"
    task.write_text("- pick: no_such_thing\n- place_on: box\n")   # refused after the twin is loaded
    with caplog.at_level(logging.WARNING, logger="splattwin"):
        assert main(["plan", str(old), "--task", str(task), "--no-render"]) == 2
    said = [r.getMessage() for r in caplog.records if "predates obstacle-only boxes" in r.getMessage()]
    assert len(said) == 1 and "'cube'" in said[0] and "robot's world" in said[0]
