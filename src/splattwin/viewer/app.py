"""Web viewer (viser) for a twin: splats, semantic labels in colour, collision meshes, the robot and
its planned trajectory played back.

`splattwin view TWIN [--host 127.0.0.1 --port 8080]` serves on loopback by default; open the printed
URL in a browser. Everything is built from the twin folder's manifest (checked: `Manifest.load`).
The viewer has no authentication: bound to any other address it warns that anyone who can reach the
machine can open it. When the asked port is busy, viser serves on the next free one and the viewer
says so.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.robot.track import RobotTrack
from splattwin.transforms import quat_wxyz_from_matrix
from splattwin.twin.manifest import Manifest

log = logging.getLogger(__name__)

def label_colors(labels: np.ndarray) -> np.ndarray:
    """[N] int labels -> [N,3] uint8 colours, the same palette as the semantic label maps
    (negative labels count as background)."""
    from splattwin.semantics.render import palette

    labels = np.maximum(np.asarray(labels, dtype=np.int64), 0)
    return palette(int(labels.max(initial=0)))[labels]


def workspace_mask(means: np.ndarray, background, margin: float = 0.3, height: float = 1.0) -> np.ndarray:
    """[N] bool: Gaussians within the table's footprint (+ margin) from below the table to `height` above."""
    xmin, xmax, ymin, ymax = background.table_extent
    z0 = background.table_height
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    return ((x > xmin - margin) & (x < xmax + margin) & (y > ymin - margin) & (y < ymax + margin)
            & (z > z0 - margin) & (z < z0 + height))


def _frame_camera(server, points: np.ndarray) -> None:
    """Initial view: from the -x/-y side, above, at a distance that frames the robust extent of `points`."""
    lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.05)
    server.initial_camera.look_at = centre
    server.initial_camera.position = centre + radius * 2.2 * np.array([-0.7, -0.5, 0.6])
    server.initial_camera.up = (0.0, 0.0, 1.0)


def _load_mesh(path: Path):
    from splattwin.meshio import load_mesh

    m = load_mesh(path, "collision mesh")
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)


def build_scene(server, twin_dir: Path, robot: RobotTrack | None = None) -> dict:
    """Populate a viser server with the twin. Returns the scene handles by name."""
    from splattwin.splat.gaussians import Gaussians

    twin_dir = Path(twin_dir)
    man = Manifest.load(twin_dir)
    handles: dict = {}
    gui = server.gui
    server.scene.set_up_direction("+z")
    server.scene.add_frame("/twin_frame", axes_length=0.1, axes_radius=0.003)

    splats_path = twin_dir / man.splats if man.splats else None
    if splats_path is not None and splats_path.is_file():
        g = Gaussians.load_ply(splats_path)
        from splattwin.limits import load_npy

        labels = load_npy(twin_dir / man.labels, "label array") if man.labels and (twin_dir / man.labels).is_file() else None
        # Splats far outside the table's workspace (the room, a far background shell) and huge haze
        # splats (> 5 cm) hide the scene from most viewpoints: they get their own layer, off by default.
        near = workspace_mask(g.means, man.background) & (g.scales.max(axis=1) < 0.05)
        g_far = g.subset(~near)
        g = g.subset(near)
        covs = g.covariances()
        _frame_camera(server, g.means[g.opacities > 0.5] if (g.opacities > 0.5).sum() > 10 else g.means)
        handles["splats"] = server.scene.add_gaussian_splats("/splats", centers=g.means, covariances=covs,
                                                             rgbs=np.clip(g.colors, 0, 1), opacities=g.opacities[:, None])
        if len(g_far):
            handles["far"] = server.scene.add_gaussian_splats(
                "/splats_far", centers=g_far.means, covariances=g_far.covariances(), rgbs=np.clip(g_far.colors, 0, 1),
                opacities=g_far.opacities[:, None], visible=False)
        if labels is not None and len(labels) == len(near):
            lab_rgb = label_colors(labels[near]).astype(np.float32) / 255.0
            handles["labels"] = server.scene.add_gaussian_splats("/labels", centers=g.means, covariances=covs,
                                                                 rgbs=lab_rgb, opacities=g.opacities[:, None], visible=False)
    for obj in man.objects:
        if not obj.usable:
            continue
        T = obj.pose
        col = tuple(int(c) for c in label_colors(np.array([obj.label]))[0])
        parts = obj.convex_parts or ([obj.collision_mesh] if obj.collision_mesh else [])
        for i, rel in enumerate(parts):
            V, F = _load_mesh(twin_dir / rel)
            handles[f"col/{obj.name}/{i}"] = server.scene.add_mesh_simple(
                f"/collision/{obj.name}/part{i}", V, F, color=col, opacity=0.6, wxyz=quat_wxyz_from_matrix(T[:3, :3]),
                position=T[:3, 3], visible=False)
    bg = man.background
    for i, rel in enumerate(bg.convex_parts or ([bg.collision_mesh] if bg.collision_mesh else [])):
        V, F = _load_mesh(twin_dir / rel)
        handles[f"col/background/{i}"] = server.scene.add_mesh_simple(f"/collision/background/part{i}", V, F,
                                                                      color=(160, 160, 160), opacity=0.5, visible=False)

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
        if "splats" in handles:
            handles["splats"].visible = show_splats.value

    @show_labels.on_update
    def _(_e) -> None:
        if "labels" in handles:
            handles["labels"].visible = show_labels.value
            if "splats" in handles:
                handles["splats"].visible = show_splats.value and not show_labels.value

    @show_coll.on_update
    def _(_e) -> None:
        for k, h in handles.items():
            if k.startswith("col/"):
                h.visible = show_coll.value

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
            # the objects' collision meshes follow the recorded motion (the splats stay where captured)
            for obj_name, poses in robot.object_poses.items():
                T = poses[t]
                for key, h in handles.items():
                    if key.startswith(f"col/{obj_name}/"):
                        h.position = T[:3, 3]
                        h.wxyz = quat_wxyz_from_matrix(T[:3, :3])

        @slider.on_update
        def _(_e) -> None:
            show(int(slider.value))

        def player() -> None:
            while True:
                time.sleep(0.05)
                if playing.value and len(robot.positions) > 1:
                    slider.value = (int(slider.value) + 1) % len(robot.positions)

        threading.Thread(target=player, daemon=True).start()
        handles["_slider"] = slider
    return handles


def load_robot_track(twin_dir: Path) -> RobotTrack | None:
    """The robot and its executed motion recorded by `splattwin plan` (robot/playback.npz), if any."""
    p = Path(twin_dir) / "robot" / "playback.npz"
    return RobotTrack.load(p) if p.is_file() else None


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
    import sys

    import viser

    twin_dir = Path(twin_dir)
    if not (twin_dir / "twin.json").is_file():
        raise InputError("not a twin folder (no twin.json)", twin_dir)
    if not 0 <= int(port) <= 65535:
        raise InputError(f"--port must be 0..65535, got {port}", "--port")
    Manifest.load(twin_dir)  # checked before the server starts
    track = load_robot_track(twin_dir)
    if not is_loopback(host):
        print(f"warning: serving on {host}, not on loopback: anyone who can reach this machine on port {port} can "
              f"open the viewer and see the twin (there is no authentication). Use --host 127.0.0.1 (the default) "
              f"to keep it local.", file=sys.stderr)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    if port != 0 and server.get_port() != port:
        print(f"note: port {port} was busy; serving on port {server.get_port()} instead", file=sys.stderr)
    build_scene(server, twin_dir, track)
    print(f"splattwin viewer: http://{host}:{server.get_port()}  (Ctrl+C to stop)")
    if not block:
        return server
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        server.stop()
    return server
