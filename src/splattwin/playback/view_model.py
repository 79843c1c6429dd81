"""What a twin looks like to the viewer and the report, without a GUI: the splats split into the workspace
layer and the far / huge background layer, label colours, the collision meshes (object parts posed by
their T_world_obj, background parts in the twin frame), and the robot's recorded motion
(robot/playback.npz, written by `splattwin plan` / the pipeline's robot stage), and with that motion the
splats themselves in motion (`MovingSplats`: the objects' Gaussians posed by the recorded object poses,
the table filled under objects that left their place; the same split as `DynamicScene`).

`splattwin.viewer` draws a `TwinView` with viser; `splattwin.report` renders its meshes into pictures.
Units: metres; colours uint8 RGB; frames: the twin frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.robot.track import RobotTrack
from splattwin.twin.manifest import Manifest

log = logging.getLogger(__name__)

HUGE_SPLAT = 0.05   # m: splats with a larger scale (haze) go to the background layer
BACKGROUND_RGB = (160, 160, 160)


def label_colors(labels: np.ndarray, where: str | Path | None = None, what: str = "labels") -> np.ndarray:
    """[N] int labels -> [N,3] uint8 colours, the same palette as the semantic label maps
    (negative labels count as background). Labels above MAX_LABEL (or not whole numbers) are an InputError
    naming `where`: a label read from a file must not size the palette (1.5e9 took 9 GB)."""
    from splattwin.errors import InputError
    from splattwin.playback.scene import MAX_LABEL
    from splattwin.semantics.label_render import palette

    labels = np.asarray(labels)
    if labels.size == 0:
        return np.zeros((0, 3), np.uint8)
    if labels.dtype.kind not in "iu":
        raise InputError(f"{what} must be whole numbers within [0, {MAX_LABEL}], got {labels.dtype} values "
                         f"({str(labels.reshape(-1)[0])[:40]}...)", where)
    hi = int(labels.max())
    if hi > MAX_LABEL:
        raise InputError(f"{what} must be within [0, {MAX_LABEL}], got {hi}", where)
    # colours of the labels present only (np.unique's inverse maps them back); the palette stays
    # the label maps' one, at most MAX_LABEL + 1 entries
    present, inverse = np.unique(np.maximum(labels.astype(np.int64), 0), return_inverse=True)
    return palette(int(present[-1]))[present][inverse.reshape(labels.shape)]


def workspace_mask(means: np.ndarray, background, margin: float = 0.3, height: float = 1.0) -> np.ndarray:
    """[N] bool: Gaussians within the table's footprint (+ margin) from below the table to `height` above."""
    xmin, xmax, ymin, ymax = background.table_extent
    z0 = background.table_height
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    return ((x > xmin - margin) & (x < xmax + margin) & (y > ymin - margin) & (y < ymax + margin)
            & (z > z0 - margin) & (z < z0 + height))


def load_robot_track(twin_dir: str | Path) -> RobotTrack | None:
    """The robot and its executed motion recorded by `splattwin plan` (robot/playback.npz), if any; None (with
    a warning) when robot/results.json says that run was made on an earlier state of the twin (a stage command
    such as `splattwin geometry` re-run into the folder since): its objects would start where they no longer
    are (`render` refuses such a rollout). Results that record no twin are played as before. A playback.npz
    that is a symbolic link out of the twin folder is an InputError naming it."""
    from splattwin.paths import confined

    twin_dir = Path(twin_dir)
    p = twin_dir / "robot" / "playback.npz"
    if not p.is_file():
        return None
    confined(twin_dir, "robot/playback.npz", p, "robot track")   # not a link to a file out of the twin
    why = _made_on_another_twin(twin_dir)
    if why is not None:
        log.warning("not showing the robot's recorded motion (%s): %s", p, why)
        return None
    return RobotTrack.load(p)


def _made_on_another_twin(twin_dir: Path) -> str | None:
    """Why robot/results.json belongs to another state of the twin, or None (it matches, or says nothing)."""
    from splattwin import io
    from splattwin.robot.outputs import results_twin

    from splattwin.paths import own_file

    results = io.read_record(own_file(twin_dir, twin_dir / "robot" / "results.json", "robot/results.json"))
    if not isinstance(results, dict) or not isinstance(results.get("twin_digest"), str):
        return None
    return results_twin(results, twin_dir)


OBSTACLE_RGB = (230, 77, 77)   # an obstacle-only box: translucent red, as in the glTF export
OBSTACLE_OPACITY = 0.5
# the viewer's collision layer over the splats: a part without its own opacity (`MeshPart.opacity`)
VIEW_OPACITY_OBJECT = 0.6
VIEW_OPACITY_BACKGROUND = 0.5


@dataclass
class MeshPart:
    """One collision part: vertices [n,3] float32 in the part's frame, faces [m,3] uint32, the part's pose
    T_world_part [4,4] (identity for background parts), colour uint8 RGB. `owner`: object name or
    "background". obstacle: the static box of an unusable object (`obstacle_only`: an estimate of where
    it stands, which the robot avoids), drawn translucent (`opacity`, else None: the drawer's default)."""

    owner: str
    index: int
    vertices: np.ndarray
    faces: np.ndarray
    T_world_part: np.ndarray
    color: tuple[int, int, int]
    obstacle: bool = False
    opacity: float | None = None

    def world_vertices(self) -> np.ndarray:
        return self.vertices @ self.T_world_part[:3, :3].T + self.T_world_part[:3, 3]

    def view_opacity(self) -> float:
        """The opacity the viewer draws this part at: its own (an obstacle box's `OBSTACLE_OPACITY`, as in
        the report and the glTF export), else the layer's default for an object's or the background's part."""
        if self.opacity is not None:
            return float(self.opacity)
        return VIEW_OPACITY_BACKGROUND if self.owner == "background" else VIEW_OPACITY_OBJECT


@dataclass
class MovingSplats:
    """The twin's splats as groups a viewer poses or shows per frame of a recorded motion (no GUI).

    static: always drawn (background and backdrop, less every residue); residue[name]: background
    Gaussians drawn only while `name` is at its twin pose (its cleaned-out Gaussians, the table under it);
    fills[name]: drawn only once `name` left (the hole fill); objects[name]: Gaussians in the object
    frame, drawn at the object's pose of the frame (`poses`). Twin frame, metres; colours view-independent
    (the viewer draws SH degree 0, so posing needs no SH rotation). relighter: the scene's re-lighting
    (`playback.relight.Relighter` over `static`), None when the twin has no light; `colours_at(k)` then
    gives each group's colours with the frame's shadows, as the renderer draws them."""

    static: object
    residue: dict
    fills: dict
    objects: dict
    T_world_obj0: dict
    poses: dict = field(default_factory=dict)     # name -> [T, 4, 4] T_world_obj per frame (the track's)
    relighter: object = None
    fill_lit0: dict = field(default_factory=dict)   # name -> capture-time lit share of the fill's sources

    @classmethod
    def from_scene(cls, scene, object_poses: dict | None = None) -> "MovingSplats":
        """Groups of a `playback.scene.DynamicScene`; object_poses: name -> [T,4,4] (e.g. a RobotTrack's)."""
        from splattwin.playback.scene import concat

        n_bg = len(scene.background)
        owner = np.full(n_bg, -1)
        names = list(scene.objects)
        for k, n in enumerate(names):   # a Gaussian in several residues goes with the first object's
            r = np.asarray(scene.residue.get(n, np.zeros(0, np.int64)), np.int64)
            r = r[owner[r] < 0]
            owner[r] = k
        static = scene.background.subset(owner < 0)
        if scene.backdrop is not None and len(scene.backdrop):
            static = concat([scene.backdrop, static], scene.sh_degree)
        relighter, fill_lit0 = None, {}
        if getattr(scene, "light", None) is not None and scene.meshes:
            from splattwin.playback.relight import Relighter

            relighter = Relighter(scene.light, scene.meshes, scene.T_world_obj0, static, scene.table_height,
                                  scene.objects, scene.unit)
            bg = scene.background
            for n, f in scene.fills.items():
                src = np.asarray(getattr(f, "source", np.zeros(0)), np.int64)
                if len(src) == len(f.gaussians) and len(src):
                    fill_lit0[n] = relighter.lit_at_capture(bg.means[src], relighter.spread(bg.quats[src], bg.scales[src]))
        return cls(static=static, residue={n: scene.background.subset(owner == k) for k, n in enumerate(names)},
                   fills={n: f.gaussians for n, f in scene.fills.items()}, objects=dict(scene.objects),
                   T_world_obj0=dict(scene.T_world_obj0),
                   poses={n: np.asarray(T, float) for n, T in (object_poses or {}).items() if n in scene.objects},
                   relighter=relighter, fill_lit0=fill_lit0)

    def __len__(self) -> int:
        return max((len(T) for T in self.poses.values()), default=1)

    def state(self, k: int) -> dict[str, tuple[np.ndarray, bool]]:
        """name -> (T_world_obj [4,4], moved) at frame k (clamped; objects without poses stay put)."""
        from splattwin.playback.scene import pose_moved

        out = {}
        for n, T0 in self.T_world_obj0.items():
            P = self.poses.get(n)
            T = P[int(np.clip(k, 0, len(P) - 1))] if P is not None and len(P) else T0
            out[n] = (T, pose_moved(T0, T))
        return out

    def colours_at(self, k: int) -> dict[str, np.ndarray]:
        """Group name ("static", "fill/<obj>", "object/<obj>") -> RGB [n,3] in [0,1] at frame k: the trained
        degree-0 colours, scaled where the frame's shadows differ from the capture's (`playback.relight`;
        unscaled without a relighter). Residue groups keep their colours (drawn only while in place)."""
        out = {"static": self.static.colors}
        out.update({f"fill/{n}": f.colors for n, f in self.fills.items()})
        out.update({f"object/{n}": g.colors for n, g in self.objects.items()})
        rl = self.relighter
        if rl is None:
            return out
        state = self.state(k)
        poses = {n: T for n, (T, _) in state.items()}
        moved = [n for n, (_, mv) in state.items() if mv]

        def apply(key: str, g, lit0, ndl0, ndl, owner=None, T=None) -> None:
            world = g.means if T is None else g.means @ T[:3, :3].T + T[:3, 3]

            def spreads_of(c):
                sp = rl.spread(g.quats[c], g.scales[c])
                return sp if sp is None or T is None else sp @ T[:3, :3].T

            f = rl.block_factors(world, lit0, ndl0, ndl, poses, moved, owner, spreads_of, every=owner in moved)
            if np.any(f != 1.0):
                out[key] = np.clip(out[key] * f[:, None], 0.0, 1.0)

        if moved:
            apply("static", self.static, rl.static_lit0, rl.static_ndl, rl.static_ndl)
            for n in moved:
                f = self.fills.get(n)
                if f is not None and len(f):   # fills: table copies, lit as their sources were, facing up
                    up = np.full(len(f), rl.L[2])
                    apply(f"fill/{n}", f, self.fill_lit0.get(n, np.ones(len(f))), up, up)
            for n, g in self.objects.items():
                if n in rl.index:
                    ndl0, ndl = rl.object_ndl(n, poses[n])
                    apply(f"object/{n}", g, rl.obj_lit0[n], ndl0, ndl, n, poses[n])
        return out

    def means_at(self, k: int) -> dict[str, np.ndarray]:
        """Group name -> world positions [n,3] of the Gaussians drawn at frame k ("static", "residue/<obj>",
        "fill/<obj>", "object/<obj>"); groups hidden at k are absent."""
        out = {"static": self.static.means}
        for n, (T, moved) in self.state(k).items():
            if moved and n in self.fills:
                out[f"fill/{n}"] = self.fills[n].means
            if not moved and len(self.residue.get(n, ())):
                out[f"residue/{n}"] = self.residue[n].means
            out[f"object/{n}"] = self.objects[n].means @ T[:3, :3].T + T[:3, 3]
        return out


@dataclass
class TwinView:
    """A twin ready to draw. splats / far: the workspace layer and the background layer (Gaussians, or
    None without splats); label_rgb: [len(splats),3] uint8 label colours of the workspace layer (None
    without labels); parts: collision parts of the usable objects and obstacle boxes of the unusable ones
    (`collision_parts`), then of the background; track: the
    robot's recorded motion, if any; motion: the splats in motion along it (`MovingSplats`), when the twin
    has object splats and a recorded track."""

    manifest: Manifest
    splats: object | None = None
    far: object | None = None
    label_rgb: np.ndarray | None = None
    parts: list[MeshPart] = field(default_factory=list)
    track: RobotTrack | None = None
    motion: MovingSplats | None = None

    @classmethod
    def load(cls, twin_dir: str | Path, meshes: bool = True, robot: bool = True) -> "TwinView":
        """Read a twin folder (checked: `Manifest.load`); meshes / robot: also the collision parts / the track."""
        twin_dir = Path(twin_dir)
        man = Manifest.load(twin_dir)
        view = cls(manifest=man)
        view._load_splats(twin_dir)
        if meshes:
            view.parts = collision_parts(twin_dir, man)
        if robot:
            view.track = load_robot_track(twin_dir)
            view.motion = load_motion(twin_dir, view.track) if view.track is not None else None
        return view

    def _load_splats(self, twin_dir: Path) -> None:
        from splattwin.playback.scene import load_labels
        from splattwin.splat.gaussians import Gaussians

        man = self.manifest
        path = twin_dir / man.splats if man.splats else None
        if path is None or not path.is_file():
            return
        g = Gaussians.load_ply(path)
        labels = None
        if man.labels and (twin_dir / man.labels).is_file():
            labels = load_labels(twin_dir / man.labels)
        # Splats far outside the table's workspace (the room, a far background shell) and huge haze
        # splats hide the scene from most viewpoints: they get their own layer.
        # (metres; an unscaled twin's nominal metre, TwinFrame.length_scale, keeps the same share of it)
        s = man.frame.length_scale()
        near = (workspace_mask(g.means, man.background, margin=0.3 * s, height=1.0 * s)
                & (g.scales.max(axis=1) < HUGE_SPLAT * s))
        self.splats, self.far = g.subset(near), g.subset(~near)
        if labels is not None and len(labels) == len(near):
            self.label_rgb = label_colors(labels[near])

    def world_meshes(self) -> list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]]:
        """[(V_world [n,3], F [m,3], rgb in 0..1)] of every collision part (for pictures)."""
        return [(p.world_vertices(), p.faces, tuple(c / 255.0 for c in p.color)) for p in self.parts]


def load_motion(twin_dir: str | Path, track: RobotTrack) -> MovingSplats | None:
    """The splats in motion along `track` (None when the twin has no object splats or the track no object
    poses). A twin whose splats cannot be split (`DynamicScene.load`'s InputError) shows them static."""
    from splattwin.errors import InputError
    from splattwin.playback.scene import DynamicScene

    if not track.object_poses:
        return None
    try:
        scene = DynamicScene.load(twin_dir)
    except InputError:
        return None
    if not scene.objects:
        return None
    return MovingSplats.from_scene(scene, track.object_poses)


def collision_parts(twin_dir: Path, man: Manifest) -> list[MeshPart]:
    """The collision parts of the usable objects (object frame, posed), the obstacle boxes of the unusable
    ones that have one (`obstacle_only`: box of bbox_extent at T_world_obj, `MeshPart.obstacle`) and the
    background's parts (twin frame)."""
    from splattwin.meshio import load_mesh

    def part(owner: str, k: int, rel: str, T: np.ndarray, color) -> MeshPart:
        m = load_mesh(Path(twin_dir) / rel, f"collision mesh of {owner!r}")
        return MeshPart(owner, k, np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32),
                        np.asarray(T, np.float64), tuple(int(c) for c in color))

    out = []
    for obj in man.objects:
        if obj.obstacle_only:   # unusable, but a static box in every collision export and the robot's world
            import trimesh

            box = trimesh.creation.box(extents=np.asarray(obj.bbox_extent, float))
            out.append(MeshPart(obj.name, 0, np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.uint32),
                                obj.pose, OBSTACLE_RGB, obstacle=True, opacity=OBSTACLE_OPACITY))
            continue
        if not obj.usable:
            continue
        col = label_colors(np.array([obj.label]), Path(twin_dir) / "twin.json", f"label of object {obj.name!r}")[0]
        for k, rel in enumerate(obj.convex_parts or ([obj.collision_mesh] if obj.collision_mesh else [])):
            out.append(part(obj.name, k, rel, obj.pose, col))
    bg = man.background
    for k, rel in enumerate(bg.convex_parts or ([bg.collision_mesh] if bg.collision_mesh else [])):
        out.append(part("background", k, rel, np.eye(4), BACKGROUND_RGB))
    return out
