"""The viewer plays the splats in motion: the data model (`MovingSplats`, no GUI) gives each frame's
splat positions from the recorded object poses; the viser GUI poses its nodes the same way."""

from __future__ import annotations

import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1]))
from playback.conftest import write_twin  # noqa: E402
from playback.rollouts import synthetic_rollout  # noqa: E402

from splattwin.playback.scene import DynamicScene  # noqa: E402
from splattwin.playback.view_model import MovingSplats, TwinView  # noqa: E402
from splattwin.robot.track import RobotTrack  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def twin_in_motion(tmp_path):
    twin = write_twin(tmp_path / "twin")
    ro = synthetic_rollout(0.6, rate=20.0)
    V = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], np.float32)
    F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.uint32)
    n = len(ro.t)
    pos = np.zeros((n, 1, 3))
    pos[:, 0, 0] = np.linspace(-0.4, -0.3, n)
    track = RobotTrack(names=["hand"], vertices=[V], faces=[F], colors=[(200, 200, 200)], positions=pos,
                       rotations=np.tile(np.eye(3), (n, 1, 1, 1)), times=ro.t, object_poses=dict(ro.object_poses))
    track.save(twin / "robot" / "playback.npz")
    return twin, ro


def test_splat_positions_follow_the_rollout(twin_in_motion):
    twin, ro = twin_in_motion
    view = TwinView.load(twin)
    mo = view.motion
    assert isinstance(mo, MovingSplats) and len(mo) == len(ro.t)
    scene = DynamicScene.load(twin)
    obj = scene.objects["blue_box"].means
    T0 = scene.T_world_obj0["blue_box"]
    for k in (0, len(ro.t) // 2, len(ro.t) - 1):
        T = ro.object_poses["blue_box"][k]
        frame = mo.means_at(k)
        np.testing.assert_allclose(frame["object/blue_box"], obj @ T[:3, :3].T + T[:3, 3], atol=1e-9)
        np.testing.assert_array_equal(frame["static"], mo.static.means)       # the background never moves
    # at the start the box is at its twin pose: its splats where captured, the table under it as captured
    f0 = mo.means_at(0)
    np.testing.assert_allclose(f0["object/blue_box"], obj @ T0[:3, :3].T + T0[:3, 3], atol=1e-9)
    assert "fill/blue_box" not in f0
    # at the end it left: the fill is drawn, the residue (table under it, cleaned-out splats) is not
    fe = mo.means_at(len(ro.t) - 1)
    assert "fill/blue_box" in fe and "residue/blue_box" not in fe
    np.testing.assert_array_equal(fe["fill/blue_box"], scene.fills["blue_box"].gaussians.means)
    # every Gaussian of the scene is in exactly one group
    n_all = len(scene.background) + len(scene.backdrop) + len(obj)
    assert len(mo.static) + len(mo.residue["blue_box"]) + len(obj) == n_all


def test_viewer_gui_poses_the_moving_splats(twin_in_motion):
    import viser

    from splattwin.transforms import quat_wxyz_from_matrix
    from splattwin.viewer.app import draw

    twin, ro = twin_in_motion
    view = TwinView.load(twin)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        h = draw(server, view)
        node = h["motion/objects/blue_box"]
        np.testing.assert_allclose(node.position, ro.object_poses["blue_box"][0][:3, 3], atol=1e-6)
        assert h["motion/residue/blue_box"].visible and not h["motion/fill/blue_box"].visible
        last = len(ro.t) - 1
        h["_slider"].value = last
        deadline = time.time() + 5.0
        T = ro.object_poses["blue_box"][last]
        while np.linalg.norm(np.asarray(node.position) - T[:3, 3]) > 1e-6 and time.time() < deadline:
            time.sleep(0.02)
        np.testing.assert_allclose(node.position, T[:3, 3], atol=1e-6)
        q = np.asarray(node.wxyz)
        q_ref = quat_wxyz_from_matrix(T[:3, :3])
        assert abs(abs(float(q @ q_ref)) - 1) < 1e-6
        assert h["motion/fill/blue_box"].visible and not h["motion/residue/blue_box"].visible
        assert h["splats"].visible
    finally:
        server.stop()
    player = h["_player"]
    player.thread.join(5.0)
    assert not player.thread.is_alive()


def test_viewer_draws_the_moved_box_shadow(tmp_path):
    """A twin with a baked shadow and a light (tests/playback/test_relight.py): the data model's colours at
    the start are the trained ones; once the box moved, the table in its old shadow is brightened by
    1/ratio and the GUI node shows those colours."""
    import viser

    from playback.test_relight import L_TRUE, OBJ_CENTRE, table_lit, write_lit_twin
    from splattwin.viewer.app import draw

    twin = write_lit_twin(tmp_path / "twin")
    ro = synthetic_rollout(0.6, rate=20.0)
    n = len(ro.t)
    T0 = DynamicScene.load(twin, relight=False).T_world_obj0["blue_box"]
    poses = np.tile(T0, (n, 1, 1))
    poses[:, 0, 3] += np.linspace(0.0, 0.12, n)
    pos = np.zeros((n, 1, 3))
    pos[:, 0, 0] = -0.4
    V = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], np.float32)
    track = RobotTrack(names=["hand"], vertices=[V], faces=[np.array([[0, 1, 2]], np.uint32)], colors=[(200, 200, 200)],
                       positions=pos, rotations=np.tile(np.eye(3), (n, 1, 1, 1)), times=ro.t,
                       object_poses={"blue_box": poses})
    track.save(twin / "robot" / "playback.npz")
    view = TwinView.load(twin)
    mo = view.motion
    assert mo.relighter is not None
    c0 = mo.colours_at(0)
    np.testing.assert_array_equal(c0["static"], mo.static.colors)
    np.testing.assert_array_equal(c0["object/blue_box"], mo.objects["blue_box"].colors)
    last = n - 1
    ce = mo.colours_at(last)
    xy = mo.static.means[:, :2]
    on_table = np.abs(mo.static.means[:, 2]) < 1e-6
    freed = on_table & (table_lit(xy, OBJ_CENTRE, L_TRUE, 0.008) == 0) & (table_lit(xy, poses[last][:3, 3], L_TRUE, 0.008) == 1)
    assert freed.sum() > 20
    ratio = mo.relighter.light.shadow_ratio
    got = ce["static"][freed] / mo.static.colors[freed]
    np.testing.assert_allclose(got, 1 / ratio, rtol=0.02)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        h = draw(server, view)
        near = h["_static_near"]
        h["_slider"].value = last
        deadline = time.time() + 5.0
        want = np.clip(ce["static"][near], 0, 1)
        while time.time() < deadline and np.abs(np.asarray(h["splats"].rgbs, float) / _scale(h["splats"].rgbs) - want).max() > 0.01:
            time.sleep(0.02)
        np.testing.assert_allclose(np.asarray(h["splats"].rgbs, float) / _scale(h["splats"].rgbs), want, atol=0.01)
    finally:
        server.stop()
    h["_player"].thread.join(5.0)


def _scale(rgbs) -> float:
    """viser may keep colours as uint8 (0..255) or floats (0..1)."""
    return 255.0 if np.asarray(rgbs).dtype == np.uint8 else 1.0


def test_viewer_label_layer_follows_the_moving_objects(twin_in_motion):
    """audit 11G: the label layer was one node of every splat at its twin pose: with labels on, a moved
    object's label colours stayed where it started while its splats and collision mesh moved."""
    import viser

    from splattwin.playback.view_model import label_colors
    from splattwin.viewer.app import draw

    twin, ro = twin_in_motion
    view = TwinView.load(twin)
    assert view.label_rgb is not None
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        h = draw(server, view)
        node = h["labels/objects/blue_box"]
        label = next(o.label for o in view.manifest.objects if o.name == "blue_box")
        rgb = np.asarray(node.rgbs)[0].astype(np.float32)
        rgb = rgb if np.asarray(node.rgbs).dtype == np.uint8 else rgb * 255   # viser keeps them as uint8
        np.testing.assert_allclose(rgb, label_colors(np.array([label]))[0], atol=1.0)
        # the static label node holds no object splat (they move with their own nodes)
        assert len(h["labels"].centers) < len(view.splats)
        last = len(ro.t) - 1
        h["_slider"].value = last
        T = ro.object_poses["blue_box"][last]
        deadline = time.time() + 5.0
        while np.linalg.norm(np.asarray(node.position) - T[:3, 3]) > 1e-6 and time.time() < deadline:
            time.sleep(0.02)
        np.testing.assert_allclose(node.position, T[:3, 3], atol=1e-6)
    finally:
        server.stop()
    h["_player"].thread.join(5.0)
