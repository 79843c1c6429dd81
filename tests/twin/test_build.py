"""Twin folder build + exporters, each checked by loading the result with the tool that consumes it."""

import warnings

import numpy as np
import pytest
import trimesh
import yaml

from splattwin.cli import main
from splattwin.scene.synthetic import synthetic_scene
from splattwin.twin.build import build_twin
from splattwin.poses.twin_frame import TwinFrame
from splattwin.twin.manifest import Manifest
from splattwin.twin.moveit import parse_scene, pose_from_msg


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    g, labels, objects, meshes = synthetic_scene(16000, seed=1, obstacle=True)
    out = tmp_path_factory.mktemp("twin")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = build_twin(g, labels, objects + [("ghost", 9, "a ghost")], out, TwinFrame("ground_truth", scaled=True),
                       formats=("urdf", "moveit", "gltf"), progress=False)
    return out, m, g, labels


def test_manifest_round_trip_and_layout(twin):
    out, m, g, labels = twin
    m2 = Manifest.load(out)
    assert m2.to_dict() == m.to_dict()
    assert m2.frame.source == "ground_truth" and m2.frame.scaled
    assert {"numpy", "trimesh", "open3d-cpu"} <= set(m2.versions)
    assert {"geometry.filter", "geometry.cluster", "geometry.mesh", "write"} <= set(m2.timings)
    assert m2.config["geometry"]["dbscan_eps"] == 0.02
    assert np.array_equal(np.load(out / m2.labels), labels)
    ghost = m2.object("ghost")
    assert not ghost.usable and "missing label" in ghost.problem and ghost.collision_mesh is None
    assert not (out / "objects" / "ghost").exists()
    for o in m2.objects:
        if not o.usable:
            continue
        for rel in [o.splat_ply, o.visual_mesh, o.collision_mesh, *o.convex_parts]:
            assert (out / rel).is_file(), rel
        col = trimesh.load(out / o.collision_mesh, force="mesh")
        assert col.is_watertight
        # object frame = centre of the box proxy, which encloses the collision mesh exactly
        assert np.allclose(col.bounds[1] - col.bounds[0], o.bbox_extent, atol=1e-6)
        assert np.allclose(col.bounds.mean(axis=0), 0.0, atol=1e-6)
        assert np.isclose(abs(col.volume), o.volume, rtol=1e-3)
    assert len(m2.object("hammer").convex_parts) >= 2
    assert (out / m2.background.collision_mesh).is_file()
    assert not list(out.rglob(".*.tmp*")) and not [p for p in out.rglob("*") if p.name.startswith(".")]


def test_object_splats_in_object_frame(twin):
    from splattwin.splat.gaussians import Gaussians

    out, m, g, labels = twin
    o = m.object("box")
    s = Gaussians.load_ply(out / o.splat_ply)
    world = s.means @ o.pose[:3, :3].T + o.pose[:3, 3]
    box_world = g.means[labels == o.label]
    # every written splat is one of the box's Gaussians, moved back to the world
    from scipy.spatial import cKDTree
    d, _ = cKDTree(box_world).query(world)
    assert d.max() < 1e-5
    assert np.abs(s.means.mean(axis=0)).max() < 0.03  # centred on the object frame


def test_urdf_loads_with_yourdfpy(twin):
    import yourdfpy

    out, m, *_ = twin
    u = yourdfpy.URDF.load(str(out / "export" / "scene.urdf"), build_collision_scene_graph=True, load_collision_meshes=True)
    assert {"world", "table", "box", "cube", "hammer", "background_obstacles"} <= set(u.link_map)
    assert len(u.link_map["background_obstacles"].collisions) == len(m.background.convex_parts) - 1 >= 1
    assert "ghost" not in u.link_map
    T = u.get_transform("hammer", "world")
    assert np.allclose(T, m.object("hammer").pose, atol=1e-5)
    assert len(u.link_map["hammer"].collisions) == len(m.object("hammer").convex_parts)
    assert np.isclose(u.link_map["box"].inertial.mass, m.object("box").mass, rtol=1e-4)
    one = yourdfpy.URDF.load(str(out / "export" / "box.urdf"), load_meshes=True)
    assert list(one.link_map) == ["box"]
    mesh_path = one.link_map["box"].visuals[0].geometry.mesh.filename
    assert mesh_path.startswith("../objects/box/")


def test_moveit_scene_text_parses_back(twin):
    out, m, *_ = twin
    name, objs = parse_scene((out / "export" / "moveit" / "scene.scene").read_text())
    by_id = {o.id: o for o in objs}
    assert name == "splattwin" and {"table", "box", "cube", "hammer", "background_obstacles"} == set(by_id)
    assert len(by_id["background_obstacles"].shapes) == len(m.background.convex_parts) - 1
    table = by_id["table"].shapes[0]
    x0, x1, y0, y1 = m.background.table_extent
    assert table.kind == "box" and np.allclose(table.size, [x1 - x0, y1 - y0, m.background.table_thickness], atol=1e-6)
    for n in ("box", "cube", "hammer"):
        o = m.object(n)
        col = trimesh.load(out / o.collision_mesh, force="mesh")
        assert np.allclose(by_id[n].T_world_obj, o.pose, atol=1e-6)
        s = by_id[n].shapes[0]
        assert s.kind == "mesh" and len(s.vertices) == len(col.vertices) and len(s.faces) == len(col.faces)
        assert np.allclose(s.vertices, col.vertices, atol=1e-6)


def test_moveit_box_proxies(twin):
    out, m, *_ = twin
    name, objs = parse_scene((out / "export" / "moveit" / "scene_boxes.scene").read_text())
    by_id = {o.id: o for o in objs}
    assert name == "splattwin_boxes"
    for n in ("box", "cube", "hammer"):
        s = by_id[n].shapes[0]
        assert s.kind == "box" and np.allclose(s.size, m.object(n).bbox_extent, atol=1e-6)
        assert np.allclose(by_id[n].T_world_obj, m.object(n).pose, atol=1e-6)
    msgs = yaml.load((out / "export" / "moveit" / "collision_objects_boxes.yaml").read_text(),
                     Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    assert all(len(c["primitives"]) == 1 and not c["meshes"] for c in msgs if c["id"] != "background_obstacles")


def test_moveit_yaml_collision_objects(twin):
    out, m, *_ = twin
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    msgs = yaml.load((out / "export" / "moveit" / "collision_objects.yaml").read_text(), Loader=loader)
    assert isinstance(msgs, list)
    by_id = {c["id"]: c for c in msgs}
    assert by_id["table"]["primitives"][0]["type"] == 1 and by_id["table"]["operation"] == 0
    h = by_id["hammer"]
    # the twin frame by name: `world` is the robot base in stock Panda MoveIt configs (audit H3)
    assert h["header"]["frame_id"] == "twin"
    assert "# frame_id twin: the twin frame" in (out / "export" / "moveit" / "collision_objects.yaml").read_text()
    assert np.allclose(pose_from_msg(h["pose"]), m.object("hammer").pose, atol=1e-6)
    col = trimesh.load(out / m.object("hammer").collision_mesh, force="mesh")
    assert len(h["meshes"][0]["vertices"]) == len(col.vertices)
    assert len(h["meshes"][0]["triangles"]) == len(col.faces) and len(h["mesh_poses"]) == 1


def test_glb_reloads_with_trimesh(twin):
    out, m, *_ = twin
    sc = trimesh.load(out / "export" / "scene.glb")
    assert {"table", "box", "cube", "hammer"} <= set(sc.graph.nodes)
    for n in ("box", "hammer"):
        vis = trimesh.load(out / m.object(n).visual_mesh, force="mesh")
        T, geom = sc.graph[n]
        g = sc.geometry[geom]
        assert len(g.faces) == len(vis.faces)
        # glb is y-up: undo the root rotation to get back the twin pose
        from splattwin.twin.gltf import Y_UP_FROM_Z_UP
        assert np.allclose(np.linalg.inv(Y_UP_FROM_Z_UP) @ T, m.object(n).pose, atol=1e-5)


def test_reexport_via_cli_replaces_files_whole(twin):
    out, m, *_ = twin
    p = out / "export" / "scene.urdf"
    before = p.read_text()
    p.write_text("garbage")
    assert main(["export", str(out), "--formats", "urdf,moveit"]) == 0
    assert p.read_text() == before
    assert Manifest.load(out).exports["urdf"] == "export/scene.urdf"
    assert main(["export", str(out), "--formats", "nope"]) == 2
    assert main(["export", str(out / "missing")]) == 2


def test_export_from_relative_folder_records_relative_paths(twin, monkeypatch):
    # `splattwin demo --out demo_out` hands the exporters a relative folder; the MJCF exporter resolves
    # paths itself, and the manifest must still record paths relative to the twin folder.
    out, *_ = twin
    monkeypatch.chdir(out.parent)
    assert main(["export", out.name, "--formats", "mjcf,urdf"]) == 0
    m = Manifest.load(out)
    assert m.exports["mjcf"] == "export/scene.xml"
    assert m.exports["urdf"] == "export/scene.urdf"


def test_export_prints_and_records_only_files_on_disk(twin, tmp_path, capsys):
    # twin.json listed moveit and gltf after `export --formats mjcf,urdf` although their files were gone
    import shutil

    out = tmp_path / "t"
    shutil.copytree(twin[0], out)
    assert {"moveit", "gltf"} <= set(Manifest.load(out).exports)   # built with them (earlier tests add more)
    shutil.rmtree(out / "export")
    capsys.readouterr()
    assert main(["export", str(out), "--formats", "mjcf,urdf"]) == 0
    printed = capsys.readouterr().out
    assert "scene.xml" in printed and "scene.urdf" in printed
    assert "moveit" not in printed and "glb" not in printed
    assert Manifest.load(out).exports == {"mjcf": "export/scene.xml", "urdf": "export/scene.urdf"}
    # an earlier export still on disk stays recorded, but only this run's files are printed
    assert main(["export", str(out), "--formats", "gltf"]) == 0
    printed = capsys.readouterr().out
    assert "scene.glb" in printed and "scene.urdf" not in printed and "scene.xml" not in printed
    exports = Manifest.load(out).exports
    assert exports == {"mjcf": "export/scene.xml", "urdf": "export/scene.urdf", "gltf": "export/scene.glb"}
    assert all((out / rel).is_file() for rel in exports.values())


def test_a_rebuild_without_an_object_leaves_none_of_its_files(twin, tmp_path):
    """A rebuild where an object is gone (masks without it) or unusable left its objects/<name>/ folder and
    export/<name>.urdf (pointing to deleted meshes) behind: only this build's objects remain."""
    import shutil

    out = tmp_path / "t"
    shutil.copytree(twin[0], out)
    _, m, g, labels = twin
    names = [o.name for o in m.objects if o.usable]
    gone, kept = names[0], names[1:]
    assert (out / "objects" / gone).is_dir() and (out / "export" / f"{gone}.urdf").is_file()
    (out / "export" / "notes.txt").write_text("mine")            # not ours to remove
    objects = [(o.name, o.label, o.prompt) for o in m.objects if o.name in kept]
    lab = np.where(np.isin(labels, [o.label for o in m.objects if o.name in kept]), labels, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(g, lab, objects, out, TwinFrame("ground_truth", scaled=True), formats=("urdf",), progress=False)
    assert not (out / "objects" / gone).exists() and not (out / "export" / f"{gone}.urdf").exists()
    assert all((out / "objects" / n).is_dir() and (out / "export" / f"{n}.urdf").is_file() for n in kept)
    assert (out / "export" / "notes.txt").read_text() == "mine" and (out / "export" / "scene.urdf").is_file()


def _missing_references(export_dir):
    """Files named in export/ (MJCF/URDF mesh file attributes) that do not exist."""
    import re

    missing = []
    for f in export_dir.rglob("*"):
        if f.suffix in (".xml", ".urdf"):
            for rel in re.findall(r'(?:file|filename)="([^"]+)"', f.read_text()):
                if not (f.parent / rel).is_file():
                    missing.append(f"{f.name} -> {rel}")
    return missing


def test_a_rebuild_with_fewer_formats_leaves_no_stale_export(twin, tmp_path):
    """A rebuild with `--export.formats mjcf` (new geometry) rewrote scene.xml only: the earlier scene.urdf,
    <object>.urdf, moveit/* and scene.glb stayed, pointing at convex parts that were gone."""
    import shutil

    from splattwin.geometry.options import GeometryOptions

    out = tmp_path / "t"
    shutil.copytree(twin[0], out)
    _, m, g, labels = twin
    objects = [(o.name, o.label, o.prompt) for o in m.objects]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(g, labels, objects, out, TwinFrame("ground_truth", scaled=True), progress=False)   # all formats
    assert {"mjcf", "urdf", "moveit", "gltf"} == set(Manifest.load(out).exports)
    assert (out / "export" / "moveit" / "scene.scene").is_file() and (out / "export" / "hammer.urdf").is_file()
    (out / "export" / "notes.txt").write_text("mine")            # not ours to remove
    (out / "export" / "moveit" / "my.launch").write_text("mine")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(g, labels, objects, out, TwinFrame("ground_truth", scaled=True), formats=("mjcf",), progress=False,
                   options=GeometryOptions(max_convex_parts=2))
    exports = Manifest.load(out).exports
    assert exports == {"mjcf": "export/scene.xml"}
    left = sorted(p.relative_to(out / "export").as_posix() for p in (out / "export").rglob("*") if p.is_file())
    assert left == ["moveit/my.launch", "notes.txt", "scene.xml"], left
    assert not _missing_references(out / "export")
    # a standalone `export` adds formats to an unchanged twin and keeps the others
    assert main(["export", str(out), "--formats", "urdf"]) == 0
    assert set(Manifest.load(out).exports) == {"mjcf", "urdf"} and not _missing_references(out / "export")
    # a rebuild with no exports at all removes every one of ours; the moveit folder goes once empty
    (out / "export" / "moveit" / "my.launch").unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(g, labels, objects, out, TwinFrame("ground_truth", scaled=True), formats=(), progress=False)
    assert Manifest.load(out).exports == {}
    assert sorted(p.name for p in (out / "export").iterdir()) == ["notes.txt"]
