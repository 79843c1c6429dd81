import socket

import numpy as np
import pytest
from PIL import Image

from splattwin.report.screenshot import screenshot
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.twin.manifest import Manifest, ObjectEntry
from splattwin.playback.view_model import label_colors
from splattwin.viewer.app import build_scene, serve


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _twin(tmp_path, n=3000):
    rng = np.random.default_rng(0)
    means = rng.uniform(-0.1, 0.1, (n, 3))
    means[:, 2] *= 0.2
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.006),
                  opacities=np.full(n, 0.9), sh=rgb_to_sh0(np.tile([[0.9, 0.1, 0.1]], (n, 1)))[:, None, :])
    (tmp_path / "splat").mkdir()
    g.save_ply(tmp_path / "splat" / "point_cloud.ply")
    labels = (means[:, 0] > 0).astype(np.int32)
    np.save(tmp_path / "labels.npy", labels)
    man = Manifest(objects=[ObjectEntry(name="box", label=1)], splats="splat/point_cloud.ply", labels="labels.npy")
    man.save(tmp_path)
    return tmp_path


def test_label_colors_distinct():
    c = label_colors(np.array([0, 1, 2, 3, 12]))
    assert len({tuple(x) for x in c[:4]}) == 4 and c.dtype == np.uint8


def test_build_scene_handles(tmp_path):
    import viser

    twin = _twin(tmp_path)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        handles = build_scene(server, twin)
        assert {"splats", "labels"} <= set(handles)
        assert handles["splats"].visible and not handles["labels"].visible
    finally:
        server.stop()


def test_collision_layer_draws_each_part_at_its_opacity_and_colour(tmp_path):
    """audit 7B: the viewer drew every object part at 0.6, an obstacle-only box too (the report, the glTF:
    0.5, red); the layer now draws what the view model gives each part."""
    import trimesh
    import viser

    from splattwin.playback.view_model import OBSTACLE_OPACITY, OBSTACLE_RGB

    twin = _twin(tmp_path)
    trimesh.creation.box(extents=[0.05, 0.05, 0.05]).export(tmp_path / "box.obj")
    man = Manifest.load(twin)
    man.objects = [ObjectEntry(name="box", label=1, collision_mesh="box.obj"),
                   ObjectEntry(name="cube", label=2, usable=False, obstacle_only=True, T_world_obj=np.eye(4).tolist(),
                               bbox_extent=[0.045, 0.045, 0.045], problem="too few points after cleaning")]
    man.save(twin)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        handles = build_scene(server, twin)
        cube, box = handles["col/cube/0"], handles["col/box/0"]
        assert cube.opacity == pytest.approx(OBSTACLE_OPACITY) and tuple(cube.color) == OBSTACLE_RGB
        assert box.opacity == pytest.approx(0.6) and tuple(box.color) != OBSTACLE_RGB
    finally:
        server.stop()


@pytest.mark.slow
def test_viewer_page_shows_content(tmp_path):
    twin = _twin(tmp_path)
    # port 0: the server binds a free port itself (a port found free and released first could be taken by
    # another process before the server binds it; the server would then serve elsewhere)
    server = serve(twin, host="127.0.0.1", port=0, block=False)
    port = server.get_port()

    def reddish(img):
        img = img.astype(int)
        return (img[..., 0] > 120) & (img[..., 0] > img[..., 1] + 50) & (img[..., 0] > img[..., 2] + 50)

    try:
        # the splats stream in over the websocket: pictures are taken until they show (or 120 s pass)
        png = screenshot(f"http://127.0.0.1:{port}/", tmp_path / "viewer.png", width=1000, height=700,
                         ready=lambda img: reddish(img).sum() > 200)
    finally:
        server.stop()
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    # Not an empty page: many distinct colours (GUI panel + 3D canvas), and the red splats are drawn.
    assert len(np.unique(img.reshape(-1, 3) // 8, axis=0)) > 20
    assert reddish(img).sum() > 200, "splats not visible in the viewer screenshot"


def test_far_and_huge_splats_get_their_own_hidden_layer(tmp_path):
    import viser

    twin = _twin(tmp_path, n=500)
    g = Gaussians.load_ply(twin / "splat" / "point_cloud.ply")
    g.means[:10] = [5.0, 0.0, 0.0]      # far outside the table
    g.scales[10:20] = 0.2                # huge haze
    g.save_ply(twin / "splat" / "point_cloud.ply")
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        h = build_scene(server, twin)
        assert not h["far"].visible and h["splats"].visible
    finally:
        server.stop()
    from splattwin.twin.manifest import Background
    from splattwin.playback.view_model import workspace_mask

    near = workspace_mask(g.means, Background())
    assert not near[:10].any() and near[10:].all()


def _track(steps: int = 5):
    from splattwin.robot.track import RobotTrack

    V = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], np.float32)
    F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.uint32)
    pos = np.zeros((steps, 1, 3))
    pos[:, 0, 2] = np.linspace(0.0, 0.2, steps)
    return RobotTrack(names=["link"], vertices=[V], faces=[F], colors=[(200, 40, 40)], positions=pos,
                      rotations=np.tile(np.eye(3), (steps, 1, 1, 1)), times=np.arange(steps) * 0.1)


def test_player_plays_and_stops_with_the_server(tmp_path):
    """Ticking Play advances the trajectory; stopping the server ends the player thread."""
    import time

    import viser

    twin = _twin(tmp_path, n=300)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        h = build_scene(server, twin, _track())
        player = h["_player"]
        assert player.thread.is_alive()
        h["_slider"].value = 0
        time.sleep(0.3)
        assert h["_slider"].value == 0                       # not playing yet
        player.playing.value = True
        deadline = time.time() + 5.0
        while h["_slider"].value == 0 and time.time() < deadline:
            time.sleep(0.02)
        assert h["_slider"].value != 0
    finally:
        server.stop()
    player.thread.join(5.0)
    assert not player.thread.is_alive(), "the player thread outlived the server"


def test_serve_stops_its_player(tmp_path):
    import threading

    twin = _twin(tmp_path, n=300)
    (twin / "robot").mkdir()
    _track().save(twin / "robot" / "playback.npz")
    server = serve(twin, host="127.0.0.1", port=_free_port(), block=False)
    players = [t for t in threading.enumerate() if t.name == "splattwin-viewer-player"]
    assert players
    server.stop()
    for t in players:
        t.join(5.0)
    assert not any(t.is_alive() for t in players)


def test_view_of_a_build_stopped_before_the_twin_says_so(tmp_path):
    """`splattwin view` on the folder of `build --until splats` said "not a twin folder (no twin.json)"."""
    from splattwin.errors import InputError

    (tmp_path / "splat").mkdir()
    (tmp_path / "splat" / "point_cloud.ply").write_bytes(b"ply\n")
    with pytest.raises(InputError, match="not a twin folder") as e:
        serve(tmp_path, port=_free_port(), block=False)
    assert "stopped before the twin stage" in str(e.value)
    with pytest.raises(InputError, match="twin folder does not exist"):   # a mistyped path
        serve(tmp_path / "nope", port=_free_port(), block=False)
