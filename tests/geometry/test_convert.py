"""End-to-end geometry on synthetic labelled Gaussians with 3DGS artefacts (known GT meshes)."""

import warnings

import numpy as np
import pytest
import trimesh

from splattwin.geometry.convert import ObjectUnusableWarning, ablation, clean_indices, convert, object_geometry
from splattwin.geometry.metrics import mesh_fidelity
from splattwin.geometry.options import GeometryOptions
from splattwin.splat.gaussians import Gaussians

from splattwin.scene.synthetic import synthetic_scene, trained_like_gaussians


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(24000, seed=0)


@pytest.fixture(scope="module")
def conversion(scene):
    g, labels, objects, _ = scene
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert(g, labels, objects, progress=False)


def test_full_cleaning_f1_and_synergy(scene):
    g, labels, objects, meshes = scene
    ab = ablation(g, labels, objects, meshes)
    for name in meshes:
        full, attr, clus, raw = (ab[c][name] for c in ("full", "attribute", "cluster", "raw"))
        assert full.f1 >= 0.95, (name, full)
        assert full.chamfer < attr.chamfer and full.chamfer < clus.chamfer and full.chamfer < raw.chamfer
        assert raw.precision < full.precision


def test_objects_are_watertight_and_posed(scene, conversion):
    _, _, _, meshes = scene
    for o in conversion.objects:
        assert o.usable, o.problem
        assert o.collision.is_watertight and o.collision.is_volume
        assert len(o.collision.faces) <= GeometryOptions().collision_faces
        gt = meshes[o.name]
        assert abs(o.volume / gt.volume - 1) < 0.25
        assert np.isclose(o.mass, o.volume * GeometryOptions().density)
        # object frame = centre of the yaw box, z up; GT mesh bottom on the table
        assert np.allclose(o.T_world_obj[:3, 2], [0, 0, 1])
        assert abs(o.T_world_obj[2, 3] - o.extent[2] / 2) < 0.004
        world = o.collision.vertices @ o.T_world_obj[:3, :3].T + o.T_world_obj[:3, 3]
        assert np.allclose(world.min(axis=0), gt.bounds[0], atol=0.006)
        assert np.allclose(world.max(axis=0), gt.bounds[1], atol=0.006)
    parts = {o.name: len(o.parts) for o in conversion.objects}
    assert parts["hammer"] >= 2 and parts["box"] == 1 and parts["cube"] == 1


def test_background_table_and_no_floaters(conversion):
    bg = conversion.background
    assert abs(bg.table_height) < 0.002
    assert np.allclose(bg.table_extent, [-0.5, 0.5, -0.4, 0.4], atol=0.01)
    assert bg.n_obstacles == 0  # the background floater blob is gone
    assert bg.collision.is_watertight


def test_background_keeps_a_standing_obstacle():
    g, labels, objects, _ = synthetic_scene(12000, seed=4, obstacle=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bg = convert(g, labels, objects[:1], progress=False).background
    assert bg.n_obstacles == 1 and len(bg.parts) == 2 and bg.collision.is_watertight
    post = bg.parts[1]
    assert np.allclose(post.bounds, [[-0.37, 0.28, 0.0], [-0.33, 0.32, 0.2]], atol=0.008)


def _blob_gaussians(pts):
    n = len(pts)
    return dict(means=pts, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.001),
                opacities=np.full(n, 0.9), sh=np.zeros((n, 1, 3)))


def test_bad_inputs_mark_objects_unusable():
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.3, 0.3, (6000, 2)), np.zeros(6000)]
    few = np.array([0.1, 0.1, 0.02]) + rng.normal(0, 0.003, (20, 3))              # too few points
    flat = np.c_[rng.uniform(-0.05, 0.05, (600, 2)) + [-0.1, 0.1], np.full(600, 0.05)]  # flat sheet
    point = np.tile([[0.0, -0.1, 0.03]], (300, 1))                                     # single point
    parts = [table, few, flat, point]
    g = Gaussians(**{k: np.concatenate([_blob_gaussians(p)[k] for p in parts]) for k in _blob_gaussians(table)})
    labels = np.concatenate([np.full(len(p), i, np.int32) for i, p in enumerate(parts)])
    objects = [("few", 1, ""), ("flat", 2, ""), ("point", 3, ""), ("missing", 7, "")]
    with pytest.warns(ObjectUnusableWarning) as rec:
        conv = convert(g, labels, objects, GeometryOptions(dbscan_voxel=0.0), progress=False)
    assert len(rec) == 4
    probs = {o.name: o.problem for o in conv.objects}
    assert all(not o.usable and o.collision is None and not o.parts for o in conv.objects)
    assert "too few points" in probs["few"]
    assert "flat" in probs["flat"]
    assert "single point" in probs["point"] or "too few" in probs["point"]
    assert "missing label" in probs["missing"]


def test_a_mesh_collapsed_to_a_sliver_marks_the_object_unusable(monkeypatch):
    """A cluster that passes the point checks but whose mesh collapses (seen on a sparse real capture: a
    7 x 1.5 x 0.7 mm tetrahedron, which MuJoCo refuses: no inertia) is unusable, not exported."""
    import splattwin.geometry.convert as C
    from splattwin.geometry.meshing import MeshResult

    rng = np.random.default_rng(1)
    cube = rng.uniform(-0.03, 0.03, (800, 3)) + [0.0, 0.0, 0.03]
    g = Gaussians(**_blob_gaussians(cube))
    opts = GeometryOptions(dbscan_voxel=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ok = object_geometry(g, np.arange(len(cube)), "cube", 1, opts)
    assert ok.usable and min(ok.extent) > 0.05
    sliver = trimesh.Trimesh([[0, 0, 0], [0.007, 0, 0], [0, 0.0015, 0], [0, 0, 0.0007]],
                             [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    assert sliver.is_watertight
    monkeypatch.setattr(C, "solid_mesh", lambda *a, **k: MeshResult(sliver, "alpha"))
    with pytest.warns(ObjectUnusableWarning, match="sliver"):
        bad = object_geometry(g, np.arange(len(cube)), "cube", 1, opts)
    assert not bad.usable and bad.collision is None and not bad.parts and "sliver" in bad.problem


def _mesh_f1(g, gt, opts: GeometryOptions):
    """Object geometry of all of `g` (one label, resting on z = 0) and its mesh fidelity vs `gt`."""
    labels = np.ones(len(g), dtype=np.int64)
    opts = opts.resolved(1.2)  # the scene scale of the embedded scene (table diagonal)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = object_geometry(g, clean_indices(g, labels, 1, opts), "obj", 1, opts, support_z=0.0)
    m = r.visual.copy()
    m.apply_transform(r.T_world_obj)
    return mesh_fidelity(m, gt), r


@pytest.mark.parametrize("shape", ["box", "cylinder"])
def test_trained_like_splats_mesh_within_5mm(shape):
    """Trained-splat artefacts (centres 1.5 sigma inside the surface, one side nearly unobserved, short
    elongated edge splats, haze): the twin mesh meets F1 >= 0.95 @ 5 mm; meshing the centres without
    the support fill (the path before issue 6) leaves an open, hollow shell."""
    if shape == "box":
        gt = trimesh.creation.box([0.12, 0.08, 0.06])
        gt.apply_translation([0, 0, 0.03])
    else:
        gt = trimesh.creation.cylinder(radius=0.035, height=0.14, sections=64)
        gt.apply_translation([0, 0, 0.07])
    g = trained_like_gaussians(gt, 2000, seed=1)
    f, r = _mesh_f1(g, gt, GeometryOptions())
    assert f.f1 >= 0.95, f
    assert r.collision.is_watertight and 0.85 < r.collision.volume / gt.volume < 1.2
    if shape == "box":  # the old path, once (it is the slow one: hollow shells go to CoACD)
        old, r_old = _mesh_f1(g, gt, GeometryOptions(densify=False, fill_to_support=False, needle_length=0.0))
        assert old.f1 < 0.9 and r_old.collision.volume < 0.5 * gt.volume, old


def test_an_object_with_an_unseen_foot_rests_on_the_table_unless_it_stands_on_another():
    """A box whose splats stop 2.5 cm above the table (a downward sweep saw little of its lower sides):
    nothing holds it in the air, so its mesh is filled down to the table (F1 as for a fully seen box). The
    same splats over another object's points (a 2 cm slab under its footprint) stand on that object:
    the mesh then ends where its splats do."""
    gt = trimesh.creation.box([0.12, 0.08, 0.06])
    gt.apply_translation([0, 0, 0.03])
    g = trained_like_gaussians(gt, 2000, seed=1)
    g = g.subset(g.means[:, 2] > 0.025)
    opts = GeometryOptions().resolved(1.2)
    idx = clean_indices(g, np.ones(len(g), dtype=np.int64), 1, opts)

    def mesh(others):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = object_geometry(g, idx, "box", 1, opts, support_z=0.0, other_points=others)
        m = r.visual.copy()
        m.apply_transform(r.T_world_obj)
        return m

    rests = mesh(None)
    assert rests.bounds[0, 2] < 0.002 and mesh_fidelity(rests, gt).f1 >= 0.95
    xy = np.random.default_rng(0).uniform([-0.05, -0.03], [0.05, 0.03], (200, 2))
    slab = np.column_stack([xy, np.full(len(xy), 0.02)])
    stands = mesh(slab)
    assert stands.bounds[0, 2] > 0.015, stands.bounds
    # points beside the footprint hold nothing up: it rests on the table again
    assert mesh(slab + [0.3, 0.0, 0.0]).bounds[0, 2] < 0.002


def test_an_object_over_a_background_obstacle_stands_on_it():
    """The background's obstacles count as supports too: a box with an unseen foot over a 2 cm slab that
    is part of the background (a plate under a cake) is not filled down through the slab."""
    gt = trimesh.creation.box([0.12, 0.08, 0.06])
    gt.apply_translation([0, 0, 0.03])
    box = trained_like_gaussians(gt, 2000, seed=1)
    box = box.subset(box.means[:, 2] > 0.025)
    xy = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 121), np.linspace(-0.3, 0.3, 121)), -1).reshape(-1, 2)
    table = np.column_stack([xy, np.zeros(len(xy))])
    slab_mesh = trimesh.creation.box([0.14, 0.10, 0.02])
    slab_mesh.apply_translation([0, 0, 0.01])
    slab = np.asarray(trimesh.sample.sample_surface_even(slab_mesh, 3000, seed=0)[0])
    slab = slab[slab[:, 2] > 0.003]

    def bottom(with_slab: bool) -> float:
        bg = np.concatenate([table, slab]) if with_slab else table
        n = len(bg)
        means = np.concatenate([bg, box.means])
        g = Gaussians(means, np.concatenate([np.tile([1.0, 0, 0, 0], (n, 1)), box.quats]),
                      np.concatenate([np.full((n, 3), 0.002), box.scales]),
                      np.concatenate([np.full(n, 0.9), box.opacities]), np.full((len(means), 1, 3), 0.2))
        labels = np.r_[np.zeros(n, np.int64), np.ones(len(box), np.int64)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            conv = convert(g, labels, [("box", 1)], GeometryOptions(max_scale=0.012), progress=False)
        if with_slab:
            assert conv.background.n_obstacles == 1
        o = conv.objects[0]
        m = o.visual.copy()
        m.apply_transform(o.T_world_obj)
        return float(m.bounds[0, 2]) - conv.background.table_height  # height above the table top

    assert bottom(False) < 0.002
    assert bottom(True) > 0.012


def _plane_gaussians(xyz: np.ndarray) -> Gaussians:
    n = len(xyz)
    return Gaussians(means=xyz, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.002),
                     opacities=np.full(n, 0.9), sh=np.full((n, 1, 3), 0.5))


def test_a_known_table_plane_beats_a_larger_far_plane_and_a_missing_table_is_a_flagged_default_under_the_objects():
    from splattwin.geometry.clustering import Plane
    from splattwin.geometry.convert import background_geometry

    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.2, 0.2, (6000, 2)), rng.normal(0, 0.0005, 6000)]
    floor = np.c_[rng.uniform(-3, 3, (24000, 2)), np.full(24000, -2.0)]  # far field: 4x the table's splats
    g = _plane_gaussians(np.concatenate([table, floor]))
    opts = GeometryOptions().resolved(2.0)
    idx = np.arange(len(g))
    fitted = background_geometry(g, idx, opts)
    # the RANSAC fit takes the far plane and finds no table on it (the cake's failure; why the prior exists)
    assert abs(fitted.plane.d - 2.0) < 0.01 and fitted.default_reason is not None
    known = background_geometry(g, idx, opts, plane=Plane(normal=np.array([0.0, 0.0, 1.0]), d=0.0))
    assert known.default_reason is None and abs(known.table_height) < 0.003
    assert np.allclose(known.table_extent, [-0.2, 0.2, -0.2, 0.2], atol=0.01)
    # only the far floor: no table splats on the plane z = 0 -> a default table, said so, under the objects
    g_far = _plane_gaussians(floor)
    objects = np.c_[rng.uniform(1.9, 2.1, (500, 2)), rng.uniform(0, 0.1, 500)]
    d = background_geometry(g_far, np.arange(len(g_far)), opts, plane=Plane(normal=np.array([0.0, 0.0, 1.0]), d=0.0),
                            length_scale=5.0, object_points=objects)
    assert d.default_reason is not None and "0 of them" in d.default_reason
    assert d.table_height == 0.0
    assert np.allclose(d.table_extent, [2.0 - 2.5, 2.0 + 2.5, 2.0 - 2.0, 2.0 + 2.0], atol=0.02)  # 1 x 0.8 m x 5
    assert np.allclose(d.collision.bounds[1, :2], [4.5, 4.0], atol=0.02)


def test_a_table_patch_beside_the_objects_is_extended_under_them_and_flagged():
    """The cake: the only table splats form a 5 cm patch away from the cake; the collision table must
    still be under the objects (they stand on it), and the twin says the table was partly assumed."""
    from splattwin.geometry.clustering import Plane
    from splattwin.geometry.convert import background_geometry

    rng = np.random.default_rng(1)
    patch = np.c_[rng.uniform(-0.45, -0.35, (3000, 2)), rng.normal(0, 0.0005, 3000)]
    g = _plane_gaussians(patch)
    objects = np.c_[rng.uniform(0.2, 0.3, (500, 2)), rng.uniform(0, 0.1, 500)]
    opts = GeometryOptions().resolved(2.0)
    z0 = Plane(normal=np.array([0.0, 0.0, 1.0]), d=0.0)
    alone = background_geometry(g, np.arange(len(g)), opts, plane=z0)   # no objects to check against
    assert alone.default_reason is None and np.allclose(alone.table_extent, [-0.45, -0.35, -0.45, -0.35], atol=0.01)
    b = background_geometry(g, np.arange(len(g)), opts, plane=z0, object_points=objects)
    x0, x1, y0, y1 = b.table_extent
    assert b.default_reason is not None and "not under the objects" in b.default_reason
    assert x0 <= -0.44 and y0 <= -0.44 and x1 >= 0.3 and y1 >= 0.3          # the patch and the objects' footprint
    assert abs(b.table_height) < 0.003
    # a table the objects stand on is used as found
    under = _plane_gaussians(np.c_[rng.uniform(0.0, 0.5, (6000, 2)), rng.normal(0, 0.0005, 6000)])
    ok = background_geometry(under, np.arange(len(under)), opts, plane=z0, object_points=objects)
    assert ok.default_reason is None and np.allclose(ok.table_extent, [0.0, 0.5, 0.0, 0.5], atol=0.01)


def test_the_table_reaches_under_an_object_its_splats_stop_short_of():
    """The audit's box thrown 74 cm: in an SfM + depth twin of `scene generate --robot-capture bop` (800
    iterations) the table splats ended under the cardboard box, so the table box did too; the box hung
    over its edge, tipped and fell to the floor when physics started. The photos show the object at rest
    on the table, so the table reaches under every object standing on it (and a margin beyond)."""
    rng = np.random.default_rng(3)
    gt = trimesh.creation.box([0.2, 0.15, 0.1])
    gt.apply_translation([0.0, 0.08, 0.05])                     # y 0.005..0.155
    gt_cube = trimesh.creation.box([0.05, 0.05, 0.05])
    gt_cube.apply_translation([0.0, -0.2, 0.025])              # the objects' middle stays over the table splats
    box, cube = trained_like_gaussians(gt, 3000, seed=3), trained_like_gaussians(gt_cube, 1500, seed=4)
    table = np.c_[rng.uniform(-0.3, 0.3, (12000, 2)), rng.normal(0, 0.0005, 12000)]
    table = table[(table[:, 1] < 0.04) & ~((np.abs(table[:, 0]) < 0.1) & (table[:, 1] > 0.005))]  # ends under the box
    table = table[~((np.abs(table[:, 0]) < 0.025) & (np.abs(table[:, 1] + 0.2) < 0.025))]
    parts = [_plane_gaussians(table), box, cube]
    g = Gaussians(**{k: np.concatenate([getattr(p, k)[:, :1] if k == "sh" else getattr(p, k) for p in parts])
                     for k in ("means", "quats", "scales", "opacities", "sh")})
    labels = np.r_[np.zeros(len(table), np.int64), np.ones(len(box), np.int64), np.full(len(cube), 2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        conv = convert(g, labels, [("box", 1, "cardboard box"), ("cube", 2, "cube")], progress=False)
    bg, (r, c) = conv.background, conv.objects
    assert r.usable and c.usable and abs(bg.table_height) < 0.003 and bg.default_reason is None
    v = r.collision.vertices @ r.T_world_obj[:3, :3].T + r.T_world_obj[:3, 3]
    assert v[:, 1].max() > 0.15 and v[:, 2].min() < 0.003          # the whole box, on the table
    x0, x1, y0, y1 = bg.table_extent
    assert y1 >= v[:, 1].max() + 0.01          # was 0.04 (the splats' edge): the box's centre (0.08) beyond it
    assert x0 <= v[:, 0].min() and x1 >= v[:, 0].max() and y0 <= -0.29   # the rest of the table as found
    # every collision export takes the table from these: the table box and the background's first part
    for m in (bg.parts[0], bg.collision):
        assert m.bounds[1, 1] >= v[:, 1].max() + 0.01
    assert np.allclose(bg.parts[0].bounds[:, :2].T.ravel(), bg.table_extent)


def test_main_parts_groups_through_touching_cells_as_documented():
    """obstacle_box's docstring said its floaters were cut at groups "chained within dbscan_eps"; the
    grouping (`main_parts`) chains through touching cells of that side: within eps always joined, a floater
    up to 2 sqrt(3) eps away may join, a farther one never. Pinned here as the docstrings now say it (kept
    over exact DBSCAN chaining, whose cost grows with the density)."""
    from splattwin.geometry.convert import main_parts

    eps = 0.02
    rng = np.random.default_rng(0)
    body = rng.uniform([0.001, 0.001, 0.001], [0.019, 0.019, 0.019], size=(200, 3))   # all in cell (0, 0, 0)
    corner = np.array([[0.0195, 0.0195, 0.0195]])

    def kept(floater):
        return bool(main_parts(np.concatenate([body, corner, [floater]]), eps)[-1])

    assert kept(corner[0] + [0.0199, 0.0, 0.0])                      # within eps: always joined
    far_but_touching = np.array([0.0399, 0.0399, 0.0399])            # in the diagonally touching cell (1, 1, 1)
    assert np.linalg.norm(far_but_touching - np.concatenate([body, corner]), axis=1).min() > 1.7 * eps
    assert kept(far_but_touching)                                    # ~1.8 eps from the rest, yet in the group
    assert not kept([0.0401, 0.0, 0.01])                             # two cells over: never (> eps of the rest here)
    assert not kept([0.0, 0.0, 2 * np.sqrt(3) * eps + 0.001])         # beyond 2 sqrt(3) eps: never


def test_convert_refuses_a_path_for_the_gaussians():
    """convert("splats.ply", ...) took the path for Gaussians and said "labels has 0 entries for 10
    Gaussians" (the path's length; audit 10A L19)."""
    with pytest.raises(TypeError, match=r"^g must be a Gaussians .*Gaussians\.load_ply.*, got str$"):
        convert("splats.ply", np.zeros(10, int), [])


def test_one_objects_gaussians_convert_with_the_whole_scenes_size_and_say_why_without(scene, caplog):
    """A notebook's `convert(g.subset(labels == k), ...)` measured max_scale (max_scale_rel x scene size) on the one
    object: ~1 mm, so the attribute filter dropped every splat and the object was unusable, "too few points after
    cleaning (0 < 20)", with nothing naming the filter (api13 D1). `scene_size` gives the whole scene's size, and
    without it the filter's drop is logged with the remedy."""
    from splattwin.geometry import scene_scale

    g, labels, objects, _ = scene
    name, label = objects[0][0], objects[0][1]
    sel = labels == label
    part = g.subset(sel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = convert(part, labels[sel], [(name, label)], background=False, progress=False,
                        scene_size=scene_scale(g.means))
        assert whole.objects[0].usable, whole.objects[0].problem
        assert whole.options.max_scale == pytest.approx(0.01 * scene_scale(g.means))
        # splats of 3 mm (a quarter of the whole scene's max_scale): the object alone, its own size (~0.2 m)
        # taken as the scene's, drops them all, and says so, naming the remedy
        part3 = Gaussians(part.means, part.quats, np.maximum(part.scales, 3e-3), part.opacities, part.sh)
        with caplog.at_level("WARNING", logger="splattwin.geometry.convert"):
            alone = convert(part3, labels[sel], [(name, label)], background=False, progress=False)
        assert not alone.objects[0].usable
        assert convert(part3, labels[sel], [(name, label)], background=False, progress=False,
                       scene_size=scene_scale(g.means)).objects[0].usable
    said = [r.getMessage() for r in caplog.records if "max_scale" in r.getMessage()]
    assert said and f"object {name!r}" in said[0] and "scene_size=" in said[0], said
    with pytest.raises(ValueError, match="scene_size"):
        convert(part, labels[sel], [(name, label)], background=False, progress=False, scene_size=float("nan"))


@pytest.mark.parametrize("objects", [["box"], "box", [("box",)], [("box", "one")], [("box", 0)], [(1, 2)],
                                     [("box", 1.5)], [("box", True)]])
def test_convert_names_a_malformed_object_list(objects):
    """convert(g, labels, ["blue_box"]) failed with "invalid literal for int() with base 10: 'l'" (the name's
    letters taken for a name and a label; api13 D2): malformed entries are an InputError saying the form, as
    build_twin's (`check_objects`, now the geometry layer's)."""
    from splattwin.errors import InputError

    g = Gaussians(**_blob_gaussians(np.random.default_rng(0).normal(0, 0.02, (60, 3))))
    with pytest.raises(InputError, match=r"^(objects must be a list of|object.* must be \(name, label, prompt\)|object "
                                         r"'box': the label must be a whole number|object 0: the name must be)"):
        convert(g, np.ones(60, int), objects, progress=False, background=False)
