"""Web viewer (viser) for a twin: splats, semantic labels in colour, collision meshes, the robot and
its planned trajectory played back. The GUI only: what is drawn comes from
`splattwin.playback.view_model.TwinView` (shared with the report). With a recorded task the splats move:
each object's Gaussians are one node posed per frame by the recorded object poses, the table under an
object that left its place shows the hole fill (`view_model.MovingSplats`).

`splattwin view TWIN [--host 127.0.0.1 --port 8080]` serves on loopback by default; open the printed
URL in a browser. Everything is built from the twin folder's manifest (checked: `Manifest.load`).
The viewer has no authentication: bound to any other address it warns that anyone who can reach the
machine can open it. When the asked port is busy, viser serves on the next free one and the viewer
says so. The trajectory player is a thread that stops with the server (`server.stop()`).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.playback.view_model import TwinView
from splattwin.transforms import quat_wxyz_from_matrix

log = logging.getLogger(__name__)


def _frame_camera(server, points: np.ndarray) -> None:
    """Initial view: from the -x/-y side, above, at a distance that frames the robust extent of `points`."""
    lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.05)
    server.initial_camera.look_at = centre
    server.initial_camera.position = centre + radius * 2.2 * np.array([-0.7, -0.5, 0.6])
    server.initial_camera.up = (0.0, 0.0, 1.0)


class Player:
    """Advances the trajectory slider while "Play" is ticked, every `period` seconds, in a daemon thread
    that ends on `stop()` (called when the server stops)."""

    def __init__(self, slider, playing, n_steps: int, period: float = 0.05):
        self.slider, self.playing, self.n_steps, self.period = slider, playing, n_steps, period
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="splattwin-viewer-player", daemon=True)

    def start(self) -> "Player":
        self.thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            if self.playing.value and self.n_steps > 1:
                self.slider.value = (int(self.slider.value) + 1) % self.n_steps

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self.thread.is_alive() and threading.current_thread() is not self.thread:
            self.thread.join(timeout)


def _stop_with_server(server, player: Player) -> None:
    """Make `server.stop()` stop the player thread first (viser has no stop callback)."""
    stop_server = server.stop

    def stop() -> None:
        player.stop()
        stop_server()
    server.stop = stop


def build_scene(server, twin_dir: Path, robot=None) -> dict:
    """Populate a viser server with the twin. robot: a `RobotTrack` to play (default: none; `serve` passes
    the twin's recorded one). Returns the scene handles by name."""
    view = TwinView.load(twin_dir, robot=False)
    view.track = robot
    if robot is not None:
        from splattwin.playback.view_model import load_motion

        view.motion = load_motion(twin_dir, robot)
    return draw(server, view)


def draw(server, view: TwinView) -> dict:
    """Draw a loaded `TwinView` on a viser server. Returns the scene handles by name."""
    handles: dict = {}
    gui = server.gui
    server.scene.set_up_direction("+z")
    s = view.manifest.frame.length_scale()  # 1 in a metric twin; an unscaled twin's nominal metre
    server.scene.add_frame("/twin_frame", axes_length=0.1 * s, axes_radius=0.003 * s)
    if not view.manifest.frame.scaled:
        gui.add_markdown("**Unscaled twin**: lengths in SfM units, not metres")

    g = view.splats
    if g is not None:
        covs = g.covariances()
        if len(g):
            _frame_camera(server, g.means[g.opacities > 0.5] if (g.opacities > 0.5).sum() > 10 else g.means)
        if view.motion is None:
            handles["splats"] = server.scene.add_gaussian_splats("/splats", centers=g.means, covariances=covs,
                                                                 rgbs=np.clip(g.colors, 0, 1),
                                                                 opacities=g.opacities[:, None])
        else:   # the splats in motion: static part, and per object its splats, residue and fill as nodes
            _add_motion(server, view, handles)
        far = view.far
        if far is not None and len(far):
            handles["far"] = server.scene.add_gaussian_splats(
                "/splats_far", centers=far.means, covariances=far.covariances(), rgbs=np.clip(far.colors, 0, 1),
                opacities=far.opacities[:, None], visible=False)
        if view.label_rgb is not None and view.motion is not None:
            _add_motion_labels(server, view, handles)
        elif view.label_rgb is not None:
            handles["labels"] = server.scene.add_gaussian_splats(
                "/labels", centers=g.means, covariances=covs, rgbs=view.label_rgb.astype(np.float32) / 255.0,
                opacities=g.opacities[:, None], visible=False)
    for p in view.parts:
        if p.owner == "background":
            handles[f"col/background/{p.index}"] = server.scene.add_mesh_simple(
                f"/collision/background/part{p.index}", p.vertices, p.faces, color=p.color,
                opacity=p.view_opacity(), visible=False)
        else:
            T = p.T_world_part
            handles[f"col/{p.owner}/{p.index}"] = server.scene.add_mesh_simple(
                f"/collision/{p.owner}/part{p.index}", p.vertices, p.faces, color=p.color, opacity=p.view_opacity(),
                wxyz=quat_wxyz_from_matrix(T[:3, :3]), position=T[:3, 3], visible=False)

    with gui.add_folder("Layers"):
        show_splats = gui.add_checkbox("Splats", True)
        show_labels = gui.add_checkbox("Labels (colour)", False)
        show_coll = gui.add_checkbox("Collision meshes", False)
        show_far = gui.add_checkbox("Far / large background splats", False)

    @show_far.on_update
    def _(_e) -> None:
        if "far" in handles:
            handles["far"].visible = show_far.value

    @show_splats.on_update
    def _(_e) -> None:
        on = show_splats.value and not show_labels.value
        for k, h in handles.items():
            if k == "splats" or k.startswith("motion/"):
                h.visible = on and _motion_visible(k, handles)

    @show_labels.on_update
    def _(_e) -> None:
        if any(k == "labels" or k.startswith("labels/") for k in handles):
            for k, h in handles.items():
                if k == "labels" or k.startswith("labels/"):
                    h.visible = show_labels.value
            for k, h in handles.items():
                if k == "splats" or k.startswith("motion/"):
                    h.visible = show_splats.value and not show_labels.value and _motion_visible(k, handles)

    @show_coll.on_update
    def _(_e) -> None:
        for k, h in handles.items():
            if k.startswith("col/"):
                h.visible = show_coll.value

    robot = view.track
    if robot is not None and len(robot.names):
        for k, name in enumerate(robot.names):
            handles[f"robot/{name}"] = server.scene.add_mesh_simple(
                f"/robot/{name}", robot.vertices[k], robot.faces[k], color=robot.colors[k],
                wxyz=quat_wxyz_from_matrix(robot.rotations[0, k]), position=robot.positions[0, k])
        with gui.add_folder("Trajectory"):
            slider = gui.add_slider("Step", min=0, max=max(len(robot.positions) - 1, 1), step=1, initial_value=0)
            playing = gui.add_checkbox("Play", False)

        def show(t: int) -> None:
            for k, name in enumerate(robot.names):
                h = handles[f"robot/{name}"]
                h.position = robot.positions[t, k]
                h.wxyz = quat_wxyz_from_matrix(robot.rotations[t, k])
            # the objects' splats and collision meshes follow the recorded motion
            if view.motion is not None:
                _show_motion(view.motion, handles, t, show_splats.value and not show_labels.value)
            for obj_name, poses in robot.object_poses.items():
                T = poses[t]
                for key, h in handles.items():
                    if key.startswith(f"col/{obj_name}/") or key == f"labels/objects/{obj_name}":
                        h.position = T[:3, 3]
                        h.wxyz = quat_wxyz_from_matrix(T[:3, :3])

        @slider.on_update
        def _(_e) -> None:
            show(int(slider.value))

        player = Player(slider, playing, len(robot.positions)).start()
        _stop_with_server(server, player)
        handles["_slider"] = slider
        handles["_player"] = player
    return handles


def _add_motion(server, view: TwinView, handles: dict) -> None:
    """Nodes of `view.motion` (`MovingSplats`): "/splats" (static, workspace part), and per object
    "/motion/objects/<name>" (object frame, posed per frame), "/motion/residue/<name>", "/motion/fill/<name>"."""
    from splattwin.playback.view_model import HUGE_SPLAT, workspace_mask

    mo = view.motion

    def add(key: str, node: str, g, visible: bool = True, T=None) -> None:
        if g is None or not len(g):
            return
        kw = {} if T is None else {"wxyz": quat_wxyz_from_matrix(T[:3, :3]), "position": T[:3, 3]}
        handles[key] = server.scene.add_gaussian_splats(node, centers=g.means, covariances=g.covariances(),
                                                        rgbs=np.clip(g.colors, 0, 1), opacities=g.opacities[:, None],
                                                        visible=visible, **kw)

    st = mo.static
    near = workspace_mask(st.means, view.manifest.background) & (st.scales.max(axis=1) < HUGE_SPLAT)
    add("splats", "/splats", st.subset(near))
    handles["_static_near"] = near
    state = mo.state(0)
    handles["_motion_state"] = {n: moved for n, (_, moved) in state.items()}
    for n in mo.objects:
        T, moved = state[n]
        add(f"motion/residue/{n}", f"/motion/residue/{n}", mo.residue.get(n), visible=not moved)
        add(f"motion/fill/{n}", f"/motion/fill/{n}", mo.fills.get(n), visible=moved)
        add(f"motion/objects/{n}", f"/motion/objects/{n}", mo.objects[n], T=T)


def _add_motion_labels(server, view: TwinView, handles: dict) -> None:
    """The label layer of splats in motion: "/labels" the static part in the background's colour and per
    object "/labels/objects/<name>" (object frame, in its label's colour) posed as its splats are; one node
    of every splat at its twin pose left a moved object's label colours where it started."""
    from splattwin.playback.view_model import HUGE_SPLAT, label_colors, workspace_mask

    mo = view.motion
    st = mo.static
    st = st.subset(workspace_mask(st.means, view.manifest.background) & (st.scales.max(axis=1) < HUGE_SPLAT))
    labels = {o.name: o.label for o in view.manifest.objects}

    def add(key: str, node: str, g, label: int, T=None) -> None:
        if g is None or not len(g):
            return
        kw = {} if T is None else {"wxyz": quat_wxyz_from_matrix(T[:3, :3]), "position": T[:3, 3]}
        rgb = np.repeat(label_colors(np.array([label]))[:1].astype(np.float32) / 255.0, len(g), axis=0)
        handles[key] = server.scene.add_gaussian_splats(node, centers=g.means, covariances=g.covariances(), rgbs=rgb,
                                                        opacities=g.opacities[:, None], visible=False, **kw)

    add("labels", "/labels", st, 0)
    state = mo.state(0)
    for n, g in mo.objects.items():
        add(f"labels/objects/{n}", f"/labels/objects/{n}", g, int(labels.get(n, 0)), T=state[n][0])


def _motion_visible(key: str, handles: dict) -> bool:
    """Whether a splat node is part of the current frame (residue/fill nodes depend on the state)."""
    state = handles.get("_motion_state", {})
    if key.startswith("motion/residue/"):
        return not state.get(key.split("/", 2)[2], False)
    if key.startswith("motion/fill/"):
        return state.get(key.split("/", 2)[2], False)
    return True


def _show_motion(motion, handles: dict, t: int, splats_on: bool) -> None:
    """Pose the object nodes for frame t; show each residue while its object is in place, its fill after."""
    state = motion.state(t)
    handles["_motion_state"] = {n: moved for n, (_, moved) in state.items()}
    for n, (T, moved) in state.items():
        h = handles.get(f"motion/objects/{n}")
        if h is not None:
            h.position = T[:3, 3]
            h.wxyz = quat_wxyz_from_matrix(T[:3, :3])
        for key, vis in ((f"motion/residue/{n}", not moved), (f"motion/fill/{n}", moved)):
            if key in handles:
                handles[key].visible = splats_on and vis
    any_moved = any(moved for _, moved in state.values())
    # the frame's shadows (playback.relight): recoloured while something is away from its place, and once
    # more when everything is back
    if getattr(motion, "relighter", None) is not None and (any_moved or handles.get("_recoloured")):
        handles["_recoloured"] = any_moved
        cols = motion.colours_at(t)
        if "splats" in handles and "_static_near" in handles:
            handles["splats"].rgbs = cols["static"][handles["_static_near"]]
        for key, rgb in cols.items():
            kind, _, name = key.partition("/")
            h = handles.get(f"motion/{'objects' if kind == 'object' else kind}/{name}") if name else None
            if h is not None:
                h.rgbs = rgb


def is_loopback(host: str) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, "localhost")."""
    import ipaddress

    if host.strip().lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to a public interface


def serve(twin_dir: str | Path, host: str = "127.0.0.1", port: int = 8080, block: bool = True):
    """Serve the interactive 3D viewer of a twin folder (viser; `splattwin view`) at http://host:port.

    block=True (the command) prints the address and serves until Ctrl-C; block=False (a notebook or script)
    logs the address and returns the running `viser.ViserServer` (call `.stop()`). port 0: any free port.
    InputError for a folder without twin.json or a bad port."""
    import viser

    twin_dir = Path(twin_dir)
    if not twin_dir.is_dir():   # a mistyped path read "not a twin folder (no twin.json)"
        raise InputError("twin folder does not exist", twin_dir)
    if not (twin_dir / "twin.json").is_file():
        from splattwin.twin.manifest import no_twin_yet

        raise InputError("not a twin folder (no twin.json)" + no_twin_yet(twin_dir), twin_dir)
    if not 0 <= int(port) <= 65535:
        raise InputError(f"--port must be 0..65535, got {port}", "--port")
    view = TwinView.load(twin_dir)  # checked before the server starts
    if not is_loopback(host):
        log.warning(f"serving on {host}, not on loopback: anyone who can reach this machine on port {port} can "
                    f"open the viewer and see the twin (there is no authentication). Use --host 127.0.0.1 (the default) "
                    f"to keep it local.")
    server = viser.ViserServer(host=host, port=port, verbose=False)
    if port != 0 and server.get_port() != port:
        log.warning("port %d was busy; serving on port %d instead", port, server.get_port())
    draw(server, view)
    if not block:   # a library call (a notebook): no print, the address in the log
        log.info("splattwin viewer: http://%s:%d", host, server.get_port())
        return server
    print(f"splattwin viewer: http://{host}:{server.get_port()}  (Ctrl+C to stop)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        server.stop()
    return server
