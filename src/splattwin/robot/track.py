"""The viewer's robot track (robot/playback.npz): the robot's visual geometry posed along a rollout.

`RobotTrack` holds per-geom meshes (geom frame) and their world poses over time, plus the objects' poses
over the same times, so a viewer draws the executed motion without MuJoCo. It is derived from the
recorded `Rollout` by forward kinematics of its full qpos (`track_from_rollout`); `write_playback` is the
one writer of robot/playback.npz (`splattwin plan` and the pipeline call it). Frames: twin (world) frame,
metres, seconds; rotations as [3,3] matrices.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.equality import dataclass_eq
from splattwin.errors import InputError

MAX_FRAMES = 300            # poses kept for playback (~10 per second of a three-step task)
MAX_GEOMS = 10_000
MAX_BYTES = 1 << 30         # uncompressed bytes of a playback file
MAX_TRACK_FRAMES = 100_000  # poses a playback file may hold (the writer keeps MAX_FRAMES)


@dataclass
class RobotTrack:
    """A robot to draw: per-geom meshes in geom frames and their world poses over time.

    positions [T, G, 3] m, rotations [T, G, 3, 3], times [T] s; object_poses: object name -> [T, 4, 4]
    T_world_obj at the same times (empty for a robot-only track)."""

    names: list[str]
    vertices: list[np.ndarray]
    faces: list[np.ndarray]
    colors: list[tuple[int, int, int]]
    positions: np.ndarray
    rotations: np.ndarray
    times: np.ndarray = field(default_factory=lambda: np.zeros(1))
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)

    __eq__ = dataclass_eq   # array-aware (splattwin.equality)

    def __len__(self) -> int:
        return len(self.positions)

    def save(self, path: str | Path) -> Path:
        """Write an .npz atomically (plain arrays only)."""
        from splattwin import io

        objs = list(self.object_poses)
        arrays = {"names": np.array(self.names, dtype=str), "colors": np.array(self.colors, np.uint8).reshape(-1, 3),
                  "positions": self.positions.astype(np.float32), "rotations": self.rotations.astype(np.float32),
                  "times": np.asarray(self.times, np.float64), "object_names": np.array(objs, dtype=str),
                  "object_poses": (np.stack([self.object_poses[o] for o in objs]).astype(np.float32) if objs
                                   else np.zeros((0, len(self.positions), 4, 4), np.float32))}
        for k in range(len(self.names)):
            arrays[f"v{k}"] = np.asarray(self.vertices[k], np.float32)
            arrays[f"f{k}"] = np.asarray(self.faces[k], np.uint32)
        return io.write_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "RobotTrack":
        """Read a playback .npz (no unpickling, sizes bounded); InputError naming the file when malformed."""
        from splattwin.limits import load_npz

        path = Path(path)
        d = load_npz(path, "robot playback track", max_bytes=MAX_BYTES, check=_check_track_headers)
        try:
            names = [str(n) for n in d["names"].reshape(-1)]
            G = len(names)
            pos, rot, times = d["positions"], d["rotations"], d["times"].reshape(-1)
            T = len(times)
            if G > MAX_GEOMS or pos.shape != (T, G, 3) or rot.shape != (T, G, 3, 3) or d["colors"].shape != (G, 3):
                raise ValueError(f"{G} geoms, positions {pos.shape}, rotations {rot.shape}, times {times.shape}")
            obj_names = [str(n) for n in d.get("object_names", np.zeros(0, str)).reshape(-1)]
            obj_poses = d.get("object_poses", np.zeros((0, T, 4, 4)))
            if obj_poses.shape != (len(obj_names), T, 4, 4):
                raise ValueError(f"{len(obj_names)} objects, object poses {obj_poses.shape}")
            verts = [d[f"v{k}"] for k in range(G)]
            faces = [d[f"f{k}"] for k in range(G)]
            for v, f in zip(verts, faces):
                if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or (f.size and f.max() >= len(v)):
                    raise ValueError("a mesh is not [V,3] vertices with [F,3] faces indexing them")
        except (KeyError, ValueError) as e:
            raise InputError(f"not a robot playback track: {e}", path) from e
        return cls(names=names, vertices=verts, faces=faces, colors=[tuple(int(c) for c in col) for col in d["colors"]],
                   positions=pos, rotations=rot, times=times,
                   object_poses={o: obj_poses[i].astype(np.float64) for i, o in enumerate(obj_names)})


def _check_track_headers(h: dict) -> str | None:
    """The track's shapes from the .npz headers alone (before any array is inflated): T frames and G geoms
    within bounds and consistent between times, positions, rotations and object poses."""
    shape = lambda k: h[k][0] if k in h else None  # noqa: E731
    times, pos = shape("times"), shape("positions")
    if times is None or pos is None or len(times) != 1 or len(pos) != 3:
        return "missing or malformed 'times' / 'positions'"
    T, G = times[0], pos[1]
    if T > MAX_TRACK_FRAMES or G > MAX_GEOMS:
        return f"{T} frames of {G} geoms, more than {MAX_TRACK_FRAMES} frames or {MAX_GEOMS} geoms"
    if pos != (T, G, 3) or shape("rotations") not in (None, (T, G, 3, 3)):
        return f"positions {pos} and rotations {shape('rotations')} do not match {T} frames of {G} geoms"
    op = shape("object_poses")
    if op is not None and (len(op) != 4 or op[0] > MAX_GEOMS or op[1:] != (T, 4, 4)):
        return f"object poses {op} do not match {T} frames"
    return None


def visual_geoms(model, bodies: set[int] | None = None) -> list[tuple[int, np.ndarray, np.ndarray, tuple[int, int, int]]]:
    """(geom id, vertices [V,3] geom frame, faces [F,3], rgb) of the visual geoms of `bodies` (all but the
    world if None): meshes and box/capsule/cylinder/sphere primitives, collision-only groups (> 2) skipped."""
    import mujoco
    import trimesh

    out = []
    for g in range(model.ngeom):
        body = model.geom_bodyid[g]
        if body == 0 or (bodies is not None and body not in bodies):
            continue
        if model.geom_group[g] > 2:  # collision-only groups in menagerie models
            continue
        gt = model.geom_type[g]
        size = model.geom_size[g]
        if gt == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            va, vn = model.mesh_vertadr[m], model.mesh_vertnum[m]
            fa, fn = model.mesh_faceadr[m], model.mesh_facenum[m]
            V, F = model.mesh_vert[va:va + vn].copy(), model.mesh_face[fa:fa + fn].copy()
        elif gt == mujoco.mjtGeom.mjGEOM_BOX:
            tm = trimesh.creation.box(extents=2 * size)
            V, F = tm.vertices, tm.faces
        elif gt == mujoco.mjtGeom.mjGEOM_CAPSULE:
            tm = trimesh.creation.capsule(height=2 * size[1], radius=size[0])
            V, F = tm.vertices, tm.faces
        elif gt == mujoco.mjtGeom.mjGEOM_CYLINDER:
            tm = trimesh.creation.cylinder(radius=size[0], height=2 * size[1])
            V, F = tm.vertices, tm.faces
        elif gt == mujoco.mjtGeom.mjGEOM_SPHERE:
            tm = trimesh.creation.icosphere(radius=size[0], subdivisions=2)
            V, F = tm.vertices, tm.faces
        else:
            continue
        rgba = model.geom_rgba[g]
        out.append((g, np.asarray(V, np.float32), np.asarray(F, np.uint32), tuple(int(255 * c) for c in rgba[:3])))
    return out


def robot_track(model, qpos: np.ndarray, times: np.ndarray | None = None, bodies: set[int] | None = None,
                object_poses: dict[str, np.ndarray] | None = None) -> RobotTrack:
    """Visual geoms of the given bodies (all non-world bodies if None), posed for each row of
    qpos [T, nq] by forward kinematics (on a scratch MjData)."""
    import mujoco

    data = mujoco.MjData(model)
    geoms = visual_geoms(model, bodies)
    qpos = np.atleast_2d(qpos)
    P = np.zeros((len(qpos), len(geoms), 3))
    R = np.zeros((len(qpos), len(geoms), 3, 3))
    ids = np.array([g for g, *_ in geoms], dtype=int)
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        P[t] = data.geom_xpos[ids]
        R[t] = data.geom_xmat[ids].reshape(-1, 3, 3)
    return RobotTrack(names=[f"g{g}" for g, *_ in geoms], vertices=[v for _, v, _, _ in geoms],
                      faces=[f for _, _, f, _ in geoms], colors=[c for *_, c in geoms], positions=P, rotations=R,
                      times=np.arange(len(qpos), dtype=float) if times is None else np.asarray(times, float),
                      object_poses=dict(object_poses or {}))


def playback_indices(t: np.ndarray, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """At most max_frames sample indices evenly spread in time over t [T] (first and last included)."""
    t = np.asarray(t, float)
    if len(t) <= max_frames:
        return np.arange(len(t))
    want = np.linspace(t[0], t[-1], max_frames)
    return np.unique(np.clip(np.searchsorted(t, want), 0, len(t) - 1))


def track_from_rollout(world, rollout, max_frames: int = MAX_FRAMES) -> RobotTrack:
    """The robot of `world` (a visual world: its visual meshes are drawn) along a rollout recorded on the
    same robot and twin, subsampled to at most max_frames poses."""
    if rollout.qpos.shape[1] != world.model.nq:
        raise ValueError(f"the rollout has {rollout.qpos.shape[1]} qpos values, the world {world.model.nq}")
    if list(rollout.joint_names) != list(world.robot.arm_joints):
        raise ValueError(f"the rollout's arm joints {rollout.joint_names} are not the world's {world.robot.arm_joints}")
    idx = playback_indices(rollout.t, max_frames)
    return robot_track(world.model, rollout.qpos[idx], rollout.t[idx], bodies=world.robot_bodies,
                       object_poses={o: T[idx] for o, T in rollout.object_poses.items()})


def write_playback(path: str | Path, world, rollout, max_frames: int = MAX_FRAMES) -> Path:
    """robot/playback.npz for the viewer from a rollout (the only writer of that file)."""
    return track_from_rollout(world, rollout, max_frames).save(path)
