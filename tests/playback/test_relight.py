"""Re-lighting (playback/relight.py): the light estimated from a twin's baked shadows, and moved objects'
shadows in the renderer's buffers, checked against an analytic shadow of a box under a known light."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.playback.relight import Occluders, estimate_light, scale_sh, shading, spread
from splattwin.splat.gaussians import SH_C0, Gaussians, rgb_to_sh0

from .conftest import OBJ_CENTRE, OBJ_HALF, make_object, make_table, write_twin

L_TRUE = np.array([-0.5, 0.6, 0.6]) / np.linalg.norm([-0.5, 0.6, 0.6])   # 35 deg up: a shadow 7 cm long
AMBIENT = 0.38


def box_shadowed(p: np.ndarray, centre: np.ndarray, half: np.ndarray, L: np.ndarray) -> np.ndarray:
    """[N] bool: the ray p + t L (t > 0) meets the axis-aligned box (slab test; independent of Open3D)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (centre - half - p) / L
        t2 = (centre + half - p) / L
    tmin = np.max(np.minimum(t1, t2), axis=1)
    tmax = np.min(np.maximum(t1, t2), axis=1)
    return (tmax >= np.maximum(tmin, 1e-6))


def table_lit(xy: np.ndarray, centre: np.ndarray, L: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """[N] lit share of table points (z = 0) beside a box of OBJ_HALF at `centre`: 1 lit, 0 shadowed,
    NaN within `margin` of a shadow edge or under the box."""
    p = np.c_[xy, np.zeros(len(xy))]
    offs = [np.zeros(3)] + [np.array([dx, dy, 0.0]) for dx in (-margin, margin) for dy in (-margin, margin)]
    sh = np.stack([box_shadowed(p + o, centre, OBJ_HALF, L) for o in offs], 1)
    out = np.where(sh.all(1), 0.0, np.where(~sh.any(1), 1.0, np.nan))
    under = np.all(np.abs(xy - centre[:2]) < OBJ_HALF[:2] + margin, axis=1)
    out[under] = np.nan
    return out


def write_lit_twin(out: Path, light: bool = True) -> Path:
    """The tiny twin (conftest) with the box's visual mesh and its shadow baked into the table under
    L_TRUE / AMBIENT (light=False: the table evenly lit, no shadow)."""
    import trimesh

    from splattwin import io
    from splattwin.twin.manifest import Manifest

    twin = write_twin(out)
    man = Manifest.load(twin)
    mesh = trimesh.creation.box(extents=2 * OBJ_HALF)
    mesh.export(twin / "objects" / "blue_box" / "visual.obj")
    man.objects[0].visual_mesh = "objects/blue_box/visual.obj"
    man.save(twin)
    full = Gaussians.load_ply(twin / "splat" / "point_cloud.ply")
    n_table = len(make_table())
    if light:
        xy = full.means[:n_table, :2]
        lit = ~box_shadowed(np.c_[xy, np.zeros(len(xy))], OBJ_CENTRE, OBJ_HALF, L_TRUE)
        rgb = (0.5 + SH_C0 * full.sh[:n_table, 0]) * shading(AMBIENT, np.full(len(xy), L_TRUE[2]), lit)[:, None]
        full.sh[:n_table, 0] = rgb_to_sh0(rgb)
        full.save_ply(twin / "splat" / "point_cloud.ply")
    return twin


@pytest.fixture(scope="module")
def lit_twin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_lit_twin(tmp_path_factory.mktemp("lit_twin"))


def test_scale_sh_scales_the_colour_in_every_direction():
    """colour(d) = 0.5 + C0 dc + view terms(d): scale_sh multiplies it by f for any direction."""
    import torch

    from splattwin.splat.sh import eval_sh

    def colour(c, d):
        return eval_sh(3, torch.from_numpy(d), torch.from_numpy(c)).numpy() + 0.5

    rng = np.random.default_rng(0)
    sh = rng.normal(0, 0.3, (50, 16, 3))
    f = rng.uniform(0.3, 2.5, 50)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    before = colour(sh, d)
    after = colour(scale_sh(sh, f), d)
    np.testing.assert_allclose(after, before * f[:, None], atol=1e-9)
    np.testing.assert_array_equal(scale_sh(sh, np.ones(50)), sh)


def test_spread_gives_the_two_longest_axes_capped():
    from splattwin.transforms import quat_wxyz_from_matrix

    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    q = quat_wxyz_from_matrix(R)[None]
    out = spread(q, np.array([[0.002, 0.03, 0.001]]), cap=0.01)
    assert out.shape == (1, 2, 3)
    np.testing.assert_allclose(out[0, 0], 0.01 * R[:, 1], atol=1e-12)    # longest (capped), the y axis
    np.testing.assert_allclose(out[0, 1], 0.002 * R[:, 0], atol=1e-12)   # second, the x axis


def test_occluders_shadow_everything_but_their_owner():
    import trimesh

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.2]
    occ = Occluders({"box": box})
    up = np.array([0.0, 0.0, 1.0])
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 0.251], [0.0, 0.0, 0.2]])
    lit = occ.lit(pts, np.full(4, -1), {"box": T}, up, 1e-3)
    np.testing.assert_array_equal(lit, [False, True, True, False])   # under it, beside it, on its top, inside it
    own = occ.lit(pts, np.zeros(4, int), {"box": T}, up, 1e-3)
    assert own.all()   # the box never shadows its own points
    stacked = Occluders({"box": box, "lid": trimesh.creation.box(extents=[0.1, 0.1, 0.01])})
    T2 = np.eye(4)
    T2[:3, 3] = [0.0, 0.0, 0.5]
    lit = stacked.lit(pts[:1], np.zeros(1, int), {"box": T, "lid": T2}, up, 1e-3)
    assert not lit[0]   # past its own box the ray meets the lid


def test_estimate_light_finds_the_baked_light(lit_twin):
    """The box's shadow baked into the table under L_TRUE: the estimate is within 2 deg and the ambient
    share within 0.05 of the truth; an evenly lit table gives no light."""
    import trimesh

    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(lit_twin)
    assert sc.light is not None
    ang = np.degrees(np.arccos(np.clip(sc.light.direction @ L_TRUE, -1, 1)))
    assert ang < 2.0, ang
    assert abs(sc.light.ambient - AMBIENT) < 0.05, sc.light
    truth = AMBIENT / (AMBIENT + (1 - AMBIENT) * L_TRUE[2])
    assert abs(sc.light.shadow_ratio - truth) < 0.05
    # the same table without a shadow, and one with too few table splats: no light
    mesh = trimesh.creation.box(extents=2 * OBJ_HALF)
    mesh.apply_translation(OBJ_CENTRE)
    table = make_table()
    assert estimate_light(table, 0.0, [mesh]) is None
    assert estimate_light(table.subset(np.arange(0, len(table), 40)), 0.0, [mesh]) is None


def test_unshadowed_twin_is_not_relit(tmp_path):
    """No light found: the renderer's buffers are the trained colours, moved or not."""
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(write_lit_twin(tmp_path / "twin", light=False))
    assert sc.light is None and sc.meshes
    T = sc.T_world_obj0["blue_box"].copy()
    T[:3, 3] += [0.12, 0.0, 0.0]
    a = PlaybackRenderer(sc, backend="cpu")
    b = PlaybackRenderer(sc, backend="cpu", relight=False)
    n = a.layout({"blue_box": T}, None)
    assert n == b.layout({"blue_box": T}, None)
    np.testing.assert_array_equal(a.sh[:n], b.sh[:n])


def test_moved_box_takes_its_shadow_along(lit_twin):
    """The box moves 12 cm: the table in its old shadow brightens by 1/ratio (the estimated light's), the
    hole fill's copies of shadowed table too, the table in its new shadow darkens by the ratio, the rest
    keeps its trained colour exactly, and back at its twin pose every buffer row is as trained."""
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(lit_twin)
    r = PlaybackRenderer(sc, backend="cpu")
    off = PlaybackRenderer(sc, backend="cpu", relight=False)
    n0 = r.layout({}, None)
    trained = r.sh[:n0].copy()
    T = sc.T_world_obj0["blue_box"].copy()
    T[:3, 3] += [0.12, 0.0, 0.0]
    n = r.layout({"blue_box": T}, None)
    assert n == off.layout({"blue_box": T}, None)
    assert r.relit_rows > 0
    colour = lambda sh: 0.5 + SH_C0 * sh[:, 0]  # noqa: E731
    ratio = r.relighter.light.shadow_ratio
    # the background (visible rows: what the fill hides at the old footprint is not drawn)
    rows = np.arange(r.n_backdrop, r.n_bg)
    rows = rows[r.opac[rows] > 0]
    xy = r.means[rows, :2].astype(float)
    on_table = np.abs(r.means[rows, 2]) < 1e-6
    old = table_lit(xy, OBJ_CENTRE, L_TRUE, margin=0.005)
    new = table_lit(xy, T[:3, 3], L_TRUE, margin=0.005)
    factor = colour(r.sh[rows]) / colour(off.sh[rows])
    freed = on_table & (old == 0) & (new == 1)
    shaded = on_table & (old == 1) & (new == 0)
    still = on_table & (old == 1) & (new == 1)
    assert freed.sum() > 50 and shaded.sum() > 50   # the test can fail
    np.testing.assert_allclose(factor[freed], 1 / ratio, rtol=0.02)
    np.testing.assert_allclose(factor[shaded], ratio, rtol=0.02)
    np.testing.assert_array_equal(r.sh[rows[still]], off.sh[rows[still]])
    # re-lit, the old shadow shows the evenly lit table (the test bakes both)
    np.testing.assert_allclose(colour(r.sh[rows[freed]]), table_colour_lit(xy[freed]), atol=0.03)
    # the fill copies table from around the footprint, shadowed sources included: lit now, as lit
    fill = sc.fills["blue_box"]
    sl = r._fill_slices["blue_box"]
    src_xy = sc.background.means[fill.source, :2]
    src_lit = table_lit(src_xy, OBJ_CENTRE, L_TRUE, margin=0.005)
    now_lit = table_lit(r.means[sl, :2].astype(float), T[:3, 3], L_TRUE, margin=0.005)
    dark = (src_lit == 0) & (now_lit == 1)
    assert dark.sum() > 20
    np.testing.assert_allclose(colour(r.sh[sl][dark]), table_colour_lit(src_xy[dark]), atol=0.03)
    # the box itself stays lit (its own mesh never shadows it; nothing else does)
    k = len(sc.objects["blue_box"])
    np.testing.assert_array_equal(r.sh[n - k:n], off.sh[n - k:n])
    # back home: as trained, bit for bit
    assert r.layout({}, None) == n0
    np.testing.assert_array_equal(r.sh[:n0], trained)


def table_colour_lit(xy: np.ndarray) -> np.ndarray:
    from .conftest import table_colour

    return table_colour(xy) * shading(AMBIENT, np.full(len(xy), L_TRUE[2]), np.ones(len(xy)))[:, None]


def test_box_moved_into_a_shadow_darkens(lit_twin):
    """A second, static caster: the box moved under a tall slab's shadow is darkened by the ratio on its
    lit faces (normals from its mesh), and not at all on faces turned away from the light."""
    import trimesh

    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(lit_twin)
    target = np.array([-0.12, -0.12, OBJ_CENTRE[2]])   # 16 cm from the box's twin pose
    slab = trimesh.creation.box(extents=[0.16, 0.16, 0.01])
    Ts = np.eye(4)
    Ts[:3, 3] = target + L_TRUE * (0.4 - target[2]) / L_TRUE[2]   # high above, its shadow on the target
    sc.meshes = {**sc.meshes, "slab": slab}
    sc.T_world_obj0 = {**sc.T_world_obj0, "slab": Ts}
    r = PlaybackRenderer(sc, backend="cpu")
    off = PlaybackRenderer(sc, backend="cpu", relight=False)
    T = sc.T_world_obj0["blue_box"].copy()
    T[:3, 3] = target
    n = r.layout({"blue_box": T}, None)
    off.layout({"blue_box": T}, None)
    k = len(sc.objects["blue_box"])
    g = make_object()
    p_obj = g.means - OBJ_CENTRE
    facing = np.zeros(k)   # n.l of each Gaussian's face (box faces from its position)
    for ax in range(3):
        on = np.abs(np.abs(p_obj[:, ax]) - OBJ_HALF[ax]) < 1e-9
        facing[on] = np.sign(p_obj[on, ax]) * L_TRUE[ax]
    colour = lambda sh: 0.5 + SH_C0 * sh[:, 0]  # noqa: E731
    f = colour(r.sh[n - k:n]) / colour(off.sh[n - k:n])
    a = r.relighter.light.ambient
    lit_face = facing > 0.2
    expect = a / (a + (1 - a) * facing[lit_face])
    frac = np.mean(np.all(np.abs(f[lit_face] - expect[:, None]) < 0.03, axis=1))
    assert frac > 0.9, frac    # footprint samples at the slab's shadow edge aside
    np.testing.assert_allclose(f[facing < 0], 1.0, atol=1e-6)


def test_render_cli_relights_unless_told(lit_twin, tmp_path, capsys):
    """`splattwin render` says which light it found and re-lights; --no-relight draws the trained colours:
    the last frames differ where the box's old shadow was (far beyond MP4 noise)."""
    from splattwin.cli import main
    from splattwin.playback.video import read_mp4

    from .rollouts import synthetic_rollout

    r = synthetic_rollout(0.3).save(tmp_path / "r.npz")
    args = ["render", str(lit_twin), "--camera", "view_0", "--out", "", "--rollout", str(r), "--fps", "20", "--no-robot"]
    args[5] = str(tmp_path / "lit.mp4")
    assert main(args) == 0
    assert "re-lit: light from the twin's shadows" in capsys.readouterr().out
    args[5] = str(tmp_path / "unlit.mp4")
    assert main(args + ["--no-relight"]) == 0
    assert "re-lit" not in capsys.readouterr().out
    a, b = read_mp4(tmp_path / "lit.mp4"), read_mp4(tmp_path / "unlit.mp4")
    d0 = np.abs(a[0].astype(float) - b[0].astype(float)).mean(-1)
    assert (d0 > 25).sum() == 0, (d0 > 25).sum()    # at rest: the same picture, codec noise aside
    d = np.abs(a[-1].astype(float) - b[-1].astype(float)).mean(-1)
    assert (d > 25).sum() > 30, (d > 25).sum()    # moved: shadows differ


def test_candidates_hold_every_row_whose_shadow_changes(lit_twin):
    """The per-frame prefilter (`Relighter.candidates`) is exact for its purpose: over random poses of the
    box (moved, lifted, turned), every background row outside the candidates has factor 1 when tested."""
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(lit_twin)
    r = PlaybackRenderer(sc, backend="cpu")
    rl = r.relighter
    bg = sc.background
    rows = np.arange(len(bg))
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(4):
        T = sc.T_world_obj0["blue_box"].copy()
        a = rng.uniform(-np.pi, np.pi)
        T[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        T[:3, 3] += [rng.uniform(-0.12, 0.12), rng.uniform(-0.12, 0.12), rng.uniform(0.0, 0.1)]
        poses = {"blue_box": T}
        cand = rl.candidates(bg.means, ["blue_box"], poses)
        assert 0 < cand.sum() < len(bg)
        f = rl.static_factors(rows, bg.means, rl.spread(bg.quats, bg.scales), poses)
        assert np.all(f[~cand] == 1.0)
        checked += int((f[cand] != 1.0).sum())
    assert checked > 100   # shadows did change inside the candidates


def test_shadow_map_of_a_plate_analytic():
    """A square plate of points 0.3 m above a floor: under a light from above it shadows the floor under it;
    tilted 45 deg it shadows the floor displaced by 0.3 m (tan 45); nothing above or beside it; its own
    points and points just under them (within eps) are not shadowed."""
    from splattwin.playback.relight import ShadowMap

    g = np.arange(-0.1, 0.1001, 0.004)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    plate = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.3)], 1)
    floor = np.array([[0.0, 0.0, 0.0], [0.09, -0.09, 0.0], [0.15, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.5],
                      [0.0, 0.0, 0.295]])
    up = ShadowMap(plate, np.array([0.0, 0.0, 1.0]), cell=0.004, eps=0.01)
    np.testing.assert_array_equal(up.shadowed(floor), [True, True, False, False, False, False])
    assert not up.shadowed(plate).any()
    L = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)   # light towards +x: the shadow falls towards -x
    tilt = ShadowMap(plate, L, cell=0.004, eps=0.01)
    shifted = floor.copy()
    shifted[:4, 0] -= 0.3
    np.testing.assert_array_equal(tilt.shadowed(shifted[:4]), [True, True, False, False])
    np.testing.assert_array_equal(tilt.shadowed(floor[:1]), [False])


def test_robot_is_shaded_by_the_twin_light():
    from splattwin.playback.relight import Light
    from splattwin.playback.robot import AMBIENT, LIGHT_DIR_WORLD, shade

    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.1, 0.9, (20, 3))
    n = rng.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    light = Light(np.array([0.0, 0.6, 0.8]), 0.3, 0.4, 20.0, 1000, 100)
    want = albedo * (0.3 + 0.7 * np.clip(n @ light.direction, 0, None))[:, None]
    np.testing.assert_allclose(shade(albedo, n, light), np.clip(want, 0, 1), atol=1e-12)
    default = albedo * (AMBIENT + (1 - AMBIENT) * np.clip(n @ LIGHT_DIR_WORLD, 0, None))[:, None]
    np.testing.assert_allclose(shade(albedo, n), np.clip(default, 0, 1), atol=1e-12)


def test_robot_casts_its_shadow_on_the_table(lit_twin):
    """The Panda reaching over the table: table rows in its shadow map darken by the ratio, the robot's
    Gaussians are not touched, robot_shadows=False and the robot parked out of the picture leave the table
    as trained."""
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.relight import ROBOT_SHADOW_CELL, ROBOT_SHADOW_EPS, ShadowMap
    from splattwin.playback.robot import RobotPose, RobotSplats
    from splattwin.playback.scene import DynamicScene

    sc = DynamicScene.load(lit_twin)
    T_base = np.eye(4)
    T_base[:3, 3] = [-0.35, 0.0, 0.0]
    rob = RobotSplats.panda(T_base)
    pose = RobotPose(np.array([0.0, 0.3, 0.0, -1.8, 0.0, 2.1, 0.78]), 0.04)
    r = PlaybackRenderer(sc, rob, backend="cpu")
    n0 = r.layout({}, None)
    trained = r.sh[:n0].copy()
    n = r.layout({}, pose)
    colour = lambda sh: 0.5 + SH_C0 * sh[:, 0]  # noqa: E731
    rows = np.arange(r.n_backdrop, r.n_bg)
    sm = ShadowMap(r.means[n0:n].astype(float), r.relighter.L, ROBOT_SHADOW_CELL, ROBOT_SHADOW_EPS)
    in_shadow = sm.shadowed(r.means[rows].astype(float)) & (r.relighter.static_lit0[rows - r.n_backdrop] == 1.0)
    assert in_shadow.sum() > 100   # the arm's shadow falls on the table: the test can fail
    f = colour(r.sh[rows]) / colour(trained[rows])
    np.testing.assert_allclose(f[in_shadow], r.relighter.light.shadow_ratio, rtol=0.02)
    np.testing.assert_array_equal(r.sh[rows[~in_shadow & (r.relighter.static_lit0[rows - r.n_backdrop] == 1.0)]],
                                  trained[rows[~in_shadow & (r.relighter.static_lit0[rows - r.n_backdrop] == 1.0)]])
    off = PlaybackRenderer(sc, rob, backend="cpu", robot_shadows=False)
    off.layout({}, pose)
    np.testing.assert_array_equal(off.sh[:n0], trained)
    assert r.layout({}, None) == n0   # robot parked out of the picture: the table as trained
    np.testing.assert_array_equal(r.sh[:n0], trained)


def test_report_light_check_picture(lit_twin, tmp_path):
    """The report's light check outlines the table the estimated light shadows (here: the baked box shadow)
    in cyan; a twin that is not re-lit has no such picture."""
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene
    from splattwin.report.playback import SHADOW_RGB, light_check_picture

    from .conftest import capture_cameras

    cam = capture_cameras(192, 144)[0]
    r = PlaybackRenderer(DynamicScene.load(lit_twin), backend="cpu")
    rgb, frac = light_check_picture(r, cam)
    cyan = np.all(np.isclose(rgb, SHADOW_RGB), axis=-1)
    assert cyan.sum() > 20 and 0.002 < frac < 0.2
    # the outline is where the baked shadow is dark: its pixels' neighbourhood holds the darkest table
    plain = r.render(cam, {}, None).rgb.mean(-1)
    from scipy import ndimage

    near = ndimage.binary_dilation(cyan, iterations=3)
    assert plain[near].min() < 0.6 * np.median(plain[plain > 0.05])
    unlit = PlaybackRenderer(DynamicScene.load(write_lit_twin(tmp_path / "t", light=False)), backend="cpu")
    assert light_check_picture(unlit, cam) is None


def test_estimate_light_bounds_its_work(lit_twin, monkeypatch):
    """More table splats than MAX_RECEIVERS: the estimate runs on a spread subsample and finds the same light."""
    import splattwin.playback.relight as relight
    from splattwin.playback.scene import DynamicScene

    full = DynamicScene.load(lit_twin).light
    monkeypatch.setattr(relight, "MAX_RECEIVERS", 3000)
    sub = DynamicScene.load(lit_twin).light
    assert sub is not None and sub.receivers == 3000 < full.receivers
    assert np.degrees(np.arccos(np.clip(sub.direction @ full.direction, -1, 1))) < 2.0
    assert abs(sub.ambient - full.ambient) < 0.05
