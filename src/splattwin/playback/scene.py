"""The twin's splats as a dynamic scene: a static background and rigid objects posed per frame.

Inputs (the twin folder, docs/CONTRACTS.md): twin.json, splat/point_cloud.ply (full scene, twin frame),
semantics/labels.npy (label per Gaussian, 0 = background) and objects/<name>/splats.ply (object frame).

Split: each usable object is its own splats.ply, moved rigidly by T_world_obj: means, orientations and
the SH colour rotated with the object (`twin.splats.transform_gaussians`, which rotates each SH degree's
coefficients; tested against evaluating the SH in the object frame). The background is every Gaussian
labelled 0 or with the label of an object that has no splats. Gaussians labelled as an object but cleaned
out of its splats.ply (translucent fringe, foot bleed) stay where they are while the object sits at its
twin pose and are hidden once it left, together with the background Gaussians under its footprint,
which the hole fill (`holes.py`) replaces.

View dependence of moved objects: the higher SH bands of an object's Gaussians hold what its colour did
across the capture's views -- reflections of the capture's lights and surroundings, and (from a few
photos) overfitting -- relative to where it stood. Once it stands elsewhere that is no longer a
prediction (the rigid rotation of the SH keeps highlights glued to the object; from directions the capture
never saw the bands extrapolate freely), so an object that moved is drawn with its degree-0 colour, the
mean over directions: the higher bands fade out linearly over the first VIEW_FADE_M (or VIEW_FADE_RAD) of
its motion, so nothing pops in a video. An approximation, documented as such: measured on the demo
twin's three-step task (bench/objects_bounds.py, sh_dc_relit) it gains 0.5 dB on the moved objects' pixels
(20.49 -> 20.99 dB; 3 held-out views +0.6 to +1.4 dB, 2 within -0.3 dB); `view_fade=False` keeps the SH.

Frames: twin (world) frame, metres. Poses: T_world_obj [4,4] per object name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.playback.holes import HoleFill, fill_hole
from splattwin.playback.relight import Light
from splattwin.splat.gaussians import Gaussians
from splattwin.twin.manifest import Manifest
from splattwin.twin.splats import sh_rotation, transform_gaussians

MOVED_POSITION = 0.002     # m: an object this far from its twin pose has left its place
MOVED_ANGLE = np.radians(1.0)
MAX_GAUSSIANS = 20_000_000
MAX_LABEL = 65535          # object labels are 16-bit, like the label images they come from
CARRY_MARGIN = 0.005      # m around an object's bounding box: its Gaussians the splats.ply lacks
CARRY_BAND = 0.004        # m above the table top (below: the table itself)
BACKDROP_MARGIN = 0.03     # m beyond the table's extent
BACKDROP_PLANE_BAND = 0.05  # m above/below the table plane
VIEW_FADE_M = 0.05         # m of motion over which a moved object's higher SH bands fade out
VIEW_FADE_RAD = np.radians(20.0)  # ... or this much rotation


def _confined(twin_dir: Path, rel: str, what: str) -> Path:
    """A path from the manifest, confined to the twin folder."""
    p = (twin_dir / rel).resolve()
    try:
        p.relative_to(twin_dir.resolve())
    except ValueError:
        raise InputError(f"{what} path {rel!r} points outside the twin folder", twin_dir / "twin.json") from None
    return p


def pose_moved(T0: np.ndarray, T: np.ndarray, tol_m: float = MOVED_POSITION, tol_rad: float = MOVED_ANGLE) -> bool:
    """True when pose T differs from T0 by more than tol_m (m) or tol_rad (rad)."""
    dp = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
    c = (np.trace(T0[:3, :3].T @ T[:3, :3]) - 1) / 2
    return dp > tol_m or float(np.arccos(np.clip(c, -1, 1))) > tol_rad


def view_weight(T0: np.ndarray, T: np.ndarray, fade_m: float = VIEW_FADE_M, fade_rad: float = VIEW_FADE_RAD) -> float:
    """Weight in [0, 1] of an object's higher SH bands at pose T, having been captured at T0: 1 at T0,
    0 once it moved fade_m (m) or turned fade_rad (rad), linear in between (the larger of the two)."""
    dp = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
    c = (np.trace(T0[:3, :3].T @ T[:3, :3]) - 1) / 2
    da = float(np.arccos(np.clip(c, -1, 1)))
    return float(np.clip(1.0 - max(dp / fade_m, da / fade_rad), 0.0, 1.0))


def fade_view_dependence(sh: np.ndarray, weight: float) -> np.ndarray:
    """SH [N,K,3] with the bands above degree 0 scaled by `weight` (in place when weight < 1)."""
    if weight < 1.0 and sh.shape[1] > 1:
        sh[:, 1:] *= weight
    return sh


def rigid_transform(g: Gaussians, T_new_old: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means [N,3], unit quats [N,4] wxyz and SH [N,K,3] of Gaussians moved by the rigid T_new_old.

    Same maths as `twin.splats.transform_gaussians` (which this stage reuses for single transforms),
    without building a new `Gaussians` (per-frame path)."""
    from splattwin.transforms import quat_mul_wxyz, quat_wxyz_from_matrix

    R, t = T_new_old[:3, :3], T_new_old[:3, 3]
    means = g.means @ R.T + t
    quats = quat_mul_wxyz(quat_wxyz_from_matrix(R, canonical=False), g.quats)
    D = sh_rotation(R.T, g.sh_degree)
    sh = np.matmul(D, g.sh)   # = einsum("kj,njc->nkc"), batched BLAS: ~10x faster at 10k Gaussians
    return means, quats, sh


@dataclass
class DynamicScene:
    """Background + rigid objects of a twin.

    background: static Gaussians (twin frame). objects: {name: Gaussians in the object frame}.
    T_world_obj0: {name: [4,4]} twin poses. residue: {name: indices into background} hidden once the
    object moved (its cleaned-out Gaussians and, with a fill, the background under its footprint).
    fills: {name: HoleFill}. table_height: m (twin frame). backdrop: static Gaussians off the table
    (outside its extent by BACKDROP_MARGIN, or below it): the capture's surroundings, which 3DGS places
    at whatever depth fitted the photos -- often in front of where the robot stands. The renderer draws
    them behind everything else (a second layer), so they never veil the robot. rasterize_mode: the
    rasterizer mode the splats were trained with (twin.json config.build.splat; "classic" when not
    recorded), which the renderer uses by default: the antialiased mode's opacity compensation is part of
    what the training fitted; eps2d: the low-pass they were trained with (px^2, `splat.config.trained_filter`)
    for the same reason. meshes: {name: trimesh} the objects' visual meshes (object frame), the shadow
    casters; light: the light estimated from the twin's shadows (`relight.estimate_light`), None when none
    was found or re-lighting is off (then nothing is re-lit); unit: twin units per metre.
    """

    background: Gaussians
    objects: dict[str, Gaussians]
    T_world_obj0: dict[str, np.ndarray]
    residue: dict[str, np.ndarray] = field(default_factory=dict)
    fills: dict[str, HoleFill] = field(default_factory=dict)
    table_height: float = 0.0
    twin_dir: Path | None = None
    backdrop: Gaussians | None = None
    view_fade: bool = True
    rasterize_mode: str = "classic"
    eps2d: float = 0.3
    meshes: dict = field(default_factory=dict)
    light: "Light | None" = None
    unit: float = 1.0

    def object_sh(self, name: str, sh: np.ndarray, T_world_obj: np.ndarray) -> np.ndarray:
        """The posed SH [N,K,3] of object `name` at T_world_obj, its view dependence faded with its
        motion from the twin pose (`view_weight`; unchanged with view_fade=False)."""
        if not self.view_fade:
            return sh
        return fade_view_dependence(sh, view_weight(self.T_world_obj0[name], np.asarray(T_world_obj, float)))

    @property
    def sh_degree(self) -> int:
        return self.background.sh_degree

    @classmethod
    def load(cls, twin_dir: str | Path, fill_holes: bool = True, carry: bool = True, view_fade: bool = True,
             relight: bool = True) -> "DynamicScene":
        """Read a twin folder. InputError when it has no splats (or they do not match the labels).

        carry: an object also takes along the Gaussians inside its bounding box (+ CARRY_MARGIN) above
        the table band that its splats.ply lacks (the geometry stage cleans the object's foot and
        fringe out of it, and labels miss some edge Gaussians); without them a moved object loses its
        bottom and its outline. view_fade: moved objects lose their view dependence (module docstring).
        relight: estimate the light from the twin's shadows (`relight.estimate_light`, ~1-2 s) so that
        moved objects cast and receive shadows (`light` stays None when no clear shadow is found)."""
        twin_dir = Path(twin_dir)
        manifest = Manifest.load(twin_dir)
        mpath = twin_dir / "twin.json"
        mode, eps2d = manifest_filter(manifest, mpath)
        if not manifest.splats:
            raise InputError("the twin has no splats (twin.json 'splats' is empty): nothing photoreal to render; "
                             "build it from photos (splattwin build) rather than from meshes", mpath)
        ply = _confined(twin_dir, manifest.splats, "splats")
        if not ply.is_file():
            raise InputError("the twin's splat file is missing", ply)
        full = Gaussians.load_ply(ply)
        if len(full) == 0:
            raise InputError("the twin's splat file holds no Gaussians", ply)
        if len(full) > MAX_GAUSSIANS:
            raise InputError(f"{len(full)} Gaussians is more than this renderer handles ({MAX_GAUSSIANS})", ply)
        labels = np.zeros(len(full), np.int64)
        if manifest.labels:
            lp = _confined(twin_dir, manifest.labels, "labels")
            labels = load_labels(lp, len(full))
        objects, poses, extents = {}, {}, {}
        for o in manifest.objects:
            if not (o.usable and o.splat_ply):
                continue
            p = _confined(twin_dir, o.splat_ply, f"object {o.name!r} splats")
            if not p.is_file():
                raise InputError(f"splats of object {o.name!r} are missing", p)
            objects[o.name] = Gaussians.load_ply(p)
            poses[o.name] = o.pose
            extents[o.name] = np.asarray(o.bbox_extent, float)
        meshes = {}
        if relight:
            from splattwin.meshio import load_mesh

            for o in manifest.objects:
                if o.name in objects and o.visual_mesh:
                    meshes[o.name] = load_mesh(_confined(twin_dir, o.visual_mesh, f"object {o.name!r} visual mesh"),
                                               f"visual mesh of object {o.name!r}")
        moving_labels = {o.label: o.name for o in manifest.objects if o.name in objects}
        # background: label 0 and the labels of objects without splats; cleaned-out object Gaussians too
        # (hidden when their object moves)
        residue: dict[str, np.ndarray] = {}
        keep = np.ones(len(full), bool)
        for lab, name in moving_labels.items():
            idx = np.flatnonzero(labels == lab)
            obj_world = objects[name].means @ poses[name][:3, :3].T + poses[name][:3, 3]
            in_obj = _match(full.means[idx], obj_world)
            # the object's own Gaussians leave the background; the rest of its label is residue
            keep[idx[in_obj]] = False
            residue[name] = idx[~in_obj]
        h = float(manifest.background.table_height)
        if carry:
            for name in objects:
                T0 = poses[name]
                cand = np.flatnonzero(keep & (full.means[:, 2] > h + CARRY_BAND))
                p_obj = (full.means[cand] - T0[:3, 3]) @ T0[:3, :3]
                inside = np.all(np.abs(p_obj) <= extents[name] / 2 + CARRY_MARGIN, axis=1)
                take = cand[inside]
                if len(take):
                    extra = transform_gaussians(full.subset(take), np.linalg.inv(T0))
                    objects[name] = concat([objects[name], extra], objects[name].sh_degree)
                    keep[take] = False
                    residue[name] = np.setdiff1d(residue[name], take)
        back = keep & _off_table(full.means, manifest.background.table_extent, h)
        front = keep & ~back
        bg_index = np.cumsum(front) - 1
        residue = {n: bg_index[r[front[r]]] for n, r in residue.items()}
        scene = cls(background=full.subset(front), objects=objects, T_world_obj0=poses, residue=residue,
                    table_height=h, twin_dir=twin_dir, backdrop=full.subset(back), view_fade=view_fade,
                    rasterize_mode=mode, eps2d=eps2d, meshes=meshes,
                    unit=manifest.frame.length_scale())
        if meshes:
            from splattwin.playback.relight import estimate_light

            world = []
            for n, m in meshes.items():
                w = m.copy()
                w.apply_transform(np.asarray(poses[n], float))
                world.append(w)
            scene.light = estimate_light(scene.background, h, world, scene.unit)
        if fill_holes:
            scene.fill_holes()
        return scene

    def fill_holes(self) -> None:
        """Compute the fill under every object at its twin pose (`holes.fill_hole`)."""
        world = {n: self.object_world_means(n) for n in self.objects}
        for name in self.objects:
            res = self.background.means[self.residue.get(name, np.zeros(0, np.int64))]
            pts = np.concatenate([world[name], res])
            others = [world[o] for o in self.objects if o != name]
            f = fill_hole(name, pts, self.background, self.table_height, other_footprints=others)
            self.fills[name] = f
            self.residue[name] = np.union1d(self.residue.get(name, np.zeros(0, np.int64)), f.hidden)

    def object_world_means(self, name: str, T_world_obj: np.ndarray | None = None) -> np.ndarray:
        T = self.T_world_obj0[name] if T_world_obj is None else T_world_obj
        return self.objects[name].means @ T[:3, :3].T + T[:3, 3]

    def moved(self, poses: dict[str, np.ndarray]) -> list[str]:
        """Objects away from their twin pose in `poses` (missing names count as unmoved)."""
        return [n for n in self.objects if n in poses and pose_moved(self.T_world_obj0[n], np.asarray(poses[n]))]

    def gaussians(self, poses: dict[str, np.ndarray] | None = None) -> Gaussians:
        """The whole scene for one state as one `Gaussians` (twin frame): background (less the residue of
        moved objects), fills of moved objects, objects at `poses` (default: their twin poses).
        The per-frame renderer (`PlaybackRenderer`) does the same into preallocated buffers."""
        poses = poses or {}
        moved = set(self.moved(poses))
        keep = np.ones(len(self.background), bool)
        for n in moved:
            keep[self.residue.get(n, np.zeros(0, np.int64))] = False
        parts = [self.backdrop] if self.backdrop is not None else []
        parts += [self.background.subset(keep)]
        parts += [self.fills[n].gaussians for n in sorted(moved) if n in self.fills]
        for n, g in self.objects.items():
            T = np.asarray(poses.get(n, self.T_world_obj0[n]))
            m, q, sh = rigid_transform(g, T)
            sh = self.object_sh(n, sh, T)
            parts.append(Gaussians(m, q, g.scales, g.opacities, _pad_sh(sh, self.sh_degree)))
        return concat(parts, self.sh_degree)


def manifest_filter(manifest: Manifest, where: Path | None = None) -> tuple[str, float]:
    """(rasterize_mode, eps2d px^2) the twin's splats were trained with (twin.json config.build.splat, see
    `splat.config.trained_filter`; ("classic", 0.3) when not recorded). InputError naming `where` for an
    unknown mode or a bad eps2d (`Manifest.render_filter`)."""
    return manifest.render_filter(where)


def _pad_sh(sh: np.ndarray, degree: int) -> np.ndarray:
    k = (degree + 1) ** 2
    if sh.shape[1] == k:
        return sh
    out = np.zeros((len(sh), k, 3))
    m = min(k, sh.shape[1])
    out[:, :m] = sh[:, :m]
    return out


def concat(parts: list[Gaussians], sh_degree: int) -> Gaussians:
    """One Gaussians of several (SH padded/truncated to `sh_degree`)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return Gaussians.empty(sh_degree)
    return Gaussians(np.concatenate([p.means for p in parts]), np.concatenate([p.quats for p in parts]),
                     np.concatenate([p.scales for p in parts]), np.concatenate([p.opacities for p in parts]),
                     np.concatenate([_pad_sh(p.sh, sh_degree) for p in parts]))


def _off_table(means: np.ndarray, extent, table_height: float, margin: float = BACKDROP_MARGIN,
               plane_band: float = BACKDROP_PLANE_BAND) -> np.ndarray:
    """[N] bool: the capture's surroundings where the robot can stand in front of them: outside the
    table's xy extent (+ margin) and above its plane (+ band). The table's edge (where the extent
    estimate is short) and everything below the top stay in the main layer, whose single depth-sorted
    pass is what the splats were trained with (moving them to the backdrop layer cost 1-2 dB)."""
    try:
        x0, x1, y0, y1 = (float(v) for v in extent)
    except (TypeError, ValueError):
        return np.zeros(len(means), bool)
    if not (x1 > x0 and y1 > y0):
        return np.zeros(len(means), bool)
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    outside = (x < x0 - margin) | (x > x1 + margin) | (y < y0 - margin) | (y > y1 + margin)
    return outside & (z > table_height + plane_band)


def _match(a: np.ndarray, b: np.ndarray, tol: float = 1e-5) -> np.ndarray:
    """[len(a)] bool: a point of `a` coincides (within tol, m) with a point of `b`."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(b).query(a, distance_upper_bound=tol)
    return np.isfinite(d)


def load_labels(path: Path, n: int | None = None) -> np.ndarray:
    """A twin's label file (one label per Gaussian, 0 = background) as int64 [n], each in [0, MAX_LABEL];
    InputError naming the file otherwise. Labels index colour tables and name objects: a float, a negative
    or a 2**62 label is a broken file, not a colour to make up."""
    from splattwin.limits import load_npy

    if not path.is_file():
        raise InputError("the twin's label file is missing", path)
    a = load_npy(path, "label array")
    if a.ndim != 1 or (n is not None and len(a) != n) or a.dtype.kind not in "iu":
        want = f"({n},) (one per Gaussian)" if n is not None else "[N] (one per Gaussian)"
        raise InputError(f"labels must be an integer array of shape {want}, got {a.dtype} {a.shape}", path)
    if len(a) and (int(a.min()) < 0 or int(a.max()) > MAX_LABEL):
        raise InputError(f"labels must be within [0, {MAX_LABEL}], got {int(a.min())} to {int(a.max())}", path)
    return a.astype(np.int64)
