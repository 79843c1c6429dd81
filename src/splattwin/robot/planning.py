"""Collision-aware joint-space motion planning: MuJoCo as the collision checker, OMPL as the planner.

* `CollisionChecker` answers "is the arm at joint configuration q (rad) clear of everything by `margin`?"
  on a private copy of the world (`MjModel` + `MjData`): the arm's joints are set to q, every other qpos
  (gripper opening, object poses) stays at the world state given at construction (or `set_world_state`).
  One query is `mj_kinematics` + `mj_collision` (~10-20 µs with the Panda on this machine).
* `plan_path` tries the straight joint-space line first (densely checked), else plans with OMPL
  (RRTConnect by default) at a coarse validity resolution, simplifies, and re-checks the result densely;
  a path that fails the dense re-check is re-planned at a finer OMPL resolution.

Safety margin: geom margins, not mj_geomDistance. The private model gets `geom_margin` set so MuJoCo's own
broad and narrow phase report every relevant pair closer than the margin (`contact.dist < margin`) in one
`mj_collision` pass. `mj_geomDistance` would need our own broad phase over all robot×world geom pairs in
Python (hundreds of calls per configuration). World geoms carry `margin`, robot geoms `self_margin`
(MuJoCo uses the larger of the two per pair), so robot-world pairs use the margin and self pairs the
self margin. `body_margin` is kept in sync (MuJoCo's broad phase reads it).

Which contacts count: pairs whose relative pose depends on the arm joints. Each body gets the set of arm
joints on its path to the world; two geoms are checked iff those sets differ, and not for adjacent links
(MoveIt's ACM does the same; MuJoCo's parent filter skips bodies welded to the world, e.g. Panda link0).
This ignores world-world contacts (objects resting on the table) and hand/finger contacts without a
per-model list, and still checks link-link self collisions and robot-world contacts. The private model's
contype/conaffinity bits are rewritten (for geoms that collide at all in the source model) so MuJoCo
skips those constant pairs in the broad phase instead of computing and discarding them. A held object
(`attach`) moves with the TCP and takes the hand's joint set: its contacts with link7/hand/fingers are
ignored, with everything else checked. `set_clearance({body: c})` widens the margin to c around chosen
static bodies (objects whose twin pose is uncertain). `allow(a, b)` / `ignore_pairs` add exceptions by body name;
`allow(a, b, penetration=p)` is the narrower exception for intended contact (fingers closing around the
target): the pair may come closer than the margin and touch, but penetrating deeper than p still counts.

Dense checks with a certificate: `path_is_valid(..., max_sweep=s)` samples each segment so no robot or
held-object point moves more than s metres between samples (a configuration-independent bound
Σ_i r_i |Δq_i|, `sweep_radii`). With every sample clear by `margin`, the continuous motion is clear of the
world by margin - s. `plan_path` uses s = margin / 2 by default; it needs fewer samples than a fixed
0.0005 rad step and says more.

Frames and units: joint values in rad (revolute) or m (prismatic); `T_tcp_obj` is a 4×4 homogeneous
transform mapping object-body-frame points to the TCP-site frame, metres.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Iterable, Sequence

import mujoco
import numpy as np

__all__ = ["CollisionChecker", "PlanningError", "plan_path", "PLANNERS", "interpolate_path", "shortcut"]

# the planner names `plan_path` accepts: declared with the option (robot.options), re-exported here
from splattwin.robot.options import PLANNERS  # noqa: E402


class PlanningError(RuntimeError):
    """No collision-free path: start/goal invalid (message names the geoms or joint), or planner timeout."""


_NO_PAIRS = np.empty((0, 2), dtype=np.int64)


def _geom_label(model: mujoco.MjModel, geom_id: int) -> str:
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom_id)
    body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[geom_id])) or "world"
    return f"{name} (body {body})" if name else f"{body}[geom {geom_id}]"


class CollisionChecker:
    """Validity of arm joint configurations against a MuJoCo world, with a safety margin.

    Args:
        model: the world model (robot + scene). Not modified: the checker keeps a private copy.
        data: world state to freeze (object poses, gripper opening); `None` uses `qpos0`.
        arm_qpos_adr: qpos addresses of the planned joints, in planning order ([7] for the Panda).
        margin: m; any robot–world contact with signed distance < margin counts as a collision.
        self_margin: m, the same for robot–robot (self) contacts (<= margin; 0 = touching is allowed).
        ignore_pairs: body-name pairs `(a, b)` whose contacts never count.
        tcp_site: name of the TCP site (needed by `attach`).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData | None, arm_qpos_adr: Sequence[int],
                 margin: float = 0.005, ignore_pairs: Iterable[tuple[str, str]] = frozenset(),
                 tcp_site: str = "tcp", self_margin: float = 0.0):
        if margin < 0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        self.model = copy.deepcopy(model)
        m = self.model
        # contacts must be generated even if the source model disabled them for its own simulation
        m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
        m.geom_gap[:] = 0.0
        self._collidable = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        self.margin = float(margin)
        self.self_margin = float(min(self_margin, margin))
        self.data = mujoco.MjData(m)
        self.qpos_adr = np.asarray(arm_qpos_adr, dtype=np.int64)
        if self.qpos_adr.ndim != 1 or len(self.qpos_adr) == 0:
            raise ValueError("arm_qpos_adr must be a non-empty 1-D sequence of qpos addresses")
        self.dof = len(self.qpos_adr)
        a0 = int(self.qpos_adr[0])
        contiguous = np.array_equal(self.qpos_adr, np.arange(a0, a0 + self.dof))
        self._qpos_slice = slice(a0, a0 + self.dof) if contiguous else None
        self.tcp_site = tcp_site
        self._tcp_site_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, tcp_site)

        # joints, limits and names of the planned coordinates
        jnt_of_adr = {int(m.jnt_qposadr[j]): j for j in range(m.njnt)
                      if int(m.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))}
        missing = [int(a) for a in self.qpos_adr if int(a) not in jnt_of_adr]
        if missing:
            raise ValueError(f"qpos addresses {missing} are not hinge/slide joints of the model")
        self.joint_ids = np.array([jnt_of_adr[int(a)] for a in self.qpos_adr])
        self.joint_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(j)) or f"joint{j}"
                            for j in self.joint_ids]
        lo = np.full(self.dof, -2 * math.pi)
        hi = np.full(self.dof, 2 * math.pi)
        for i, j in enumerate(self.joint_ids):
            if m.jnt_limited[j]:
                lo[i], hi[i] = m.jnt_range[j]
        self.lower, self.upper = lo, hi
        self._lower_list, self._upper_list = lo.tolist(), hi.tolist()

        # bitmask of arm joints on each body's path to the world
        bit_of_jnt = {int(j): 1 << i for i, j in enumerate(self.joint_ids)}
        body_mask = np.zeros(m.nbody, dtype=np.int64)
        for b in range(1, m.nbody):  # parents precede children in MuJoCo's body order
            own = 0
            for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
                own |= bit_of_jnt.get(j, 0)
            body_mask[b] = body_mask[m.body_parentid[b]] | own
        self._body_mask = body_mask
        # adjacent links touch by construction (MoveIt's ACM disables them too); MuJoCo's filterparent
        # does not cover a link whose parent is welded to the world (Panda link0-link1)
        self._adjacent = {frozenset((b, int(m.body_parentid[b]))) for b in range(1, m.nbody)
                          if m.body_parentid[b] != 0 and (body_mask[b] or body_mask[m.body_parentid[b]])}
        self._static_robot = np.zeros(m.nbody, dtype=bool)
        for b in range(1, m.nbody):
            p = int(m.body_parentid[b])
            if body_mask[b] and not body_mask[p] and p != 0:
                self._static_robot[p] = True
        self._ignored: set[frozenset[int]] = set()
        self._touching: dict[frozenset[int], float] = {}   # pair -> allowed penetration depth (m)
        for a, b in ignore_pairs:
            self._ignored.add(frozenset((self._body_id(a), self._body_id(b))))
        self._attached: tuple[int, int, np.ndarray] | None = None  # (body id, qpos adr, T_tcp_obj)
        self._clearance: dict[int, float] = {}   # body id -> margin (m) against the robot, when > margin
        self.set_world_state(data)
        self._rebuild_pair_mask()

    # ---- world state -------------------------------------------------------------------------------
    def set_world_state(self, data: mujoco.MjData | None) -> None:
        """Freeze a new world state (all qpos and mocap poses copied from `data`; qpos0 when None)."""
        d = self.data
        if data is None:
            d.qpos[:] = self.model.qpos0
        else:
            if data.qpos.shape != d.qpos.shape:
                raise ValueError("data does not belong to this model (qpos size differs)")
            d.qpos[:] = data.qpos
            d.mocap_pos[:] = data.mocap_pos
            d.mocap_quat[:] = data.mocap_quat
        self._qpos_world = d.qpos.copy()

    def _body_id(self, name: str) -> int:
        i = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if i < 0:
            raise ValueError(f"no body named {name!r} in the model")
        return i

    def _rebuild_pair_mask(self) -> None:
        m = self.model
        mask = self._body_mask.copy()
        if self._attached is not None:
            tcp_body = int(m.site_bodyid[self._tcp_site_id])
            mask[self._attached[0]] = mask[tcp_body]
        gmask = mask[m.geom_bodyid]
        moving = gmask != 0
        # per-geom margin: MuJoCo uses max(margin1, margin2) for a pair, so world geoms carry the world
        # margin and robot geoms the (smaller) self-collision margin; robot-robot pairs then only produce
        # contacts within self_margin, which keeps the fixed finger/hand pairs out of the contact list
        m.geom_margin[:] = np.where(moving, self.self_margin, self.margin)
        # Broad-phase filter through contype/conaffinity bits on collidable geoms, so MuJoCo never computes
        # pairs whose relative pose cannot change with q (they would be ignored anyway, but cost
        # narrow-phase time on every check: objects resting on the table, the held object in the fingers):
        #   W world, R moving links, H "hand group" (rigid with the last arm link: link7, hand, fingers),
        #   A held object; the static robot base gets R/R (self collisions only, not the table it stands
        #   on). Pairs collide iff (ct1 & ca2) | (ct2 & ca1).
        W, R, H, A = 1 << 30, 1 << 29, 1 << 28, 1 << 27
        full = (1 << self.dof) - 1
        collidable = self._collidable
        held = np.zeros(m.ngeom, dtype=bool)
        if self._attached is not None:
            held = m.geom_bodyid == self._attached[0]
        hand = (gmask == full) & ~held
        arm = moving & ~hand & ~held
        base = self._static_robot[m.geom_bodyid] & ~moving
        world = ~moving & ~base
        ct = np.select([world, arm, hand, held, base], [W, R, H, A, R], 0)
        ca = np.select([world, arm, hand, held, base], [0, W | R | H | A, W | R, W | R, R], 0)
        m.geom_contype[:] = np.where(collidable, ct, 0)
        m.geom_conaffinity[:] = np.where(collidable, ca, 0)
        m.geom_margin[base] = self.self_margin
        gb = m.geom_bodyid
        # larger clearance around some static bodies (movable objects whose twin pose is uncertain)
        wide = np.zeros(m.ngeom, dtype=bool)
        wide_c = np.zeros(m.ngeom)
        for b, c in self._clearance.items():
            sel = (gb == b) & ~moving
            wide |= sel
            wide_c[sel] = c
        m.geom_margin[wide] = np.maximum(m.geom_margin[wide], wide_c[wide])
        # the broad phase uses the compiled per-body margin (max over its geoms): keep it in sync
        m.body_margin[:] = 0.0
        np.maximum.at(m.body_margin, m.geom_bodyid, m.geom_margin)
        check = gmask[:, None] != gmask[None, :]
        # count threshold per pair: world margin against the world, self margin robot-robot
        self._thr = np.where(moving[:, None] & moving[None, :], self.self_margin, self.margin)
        if wide.any():
            pairs = moving[:, None] & wide[None, :]
            self._thr = np.where(pairs, np.maximum(self._thr, wide_c[None, :]), self._thr)
            self._thr = np.where(pairs.T, np.maximum(self._thr, wide_c[:, None]), self._thr)
        for pair in self._ignored | self._adjacent:
            ids = tuple(pair) if len(pair) == 2 else (next(iter(pair)),) * 2
            sel_a = gb == ids[0]
            sel_b = gb == ids[1]
            check[np.ix_(sel_a, sel_b)] = False
            check[np.ix_(sel_b, sel_a)] = False
        for pair, depth in self._touching.items():
            ids = tuple(pair) if len(pair) == 2 else (next(iter(pair)),) * 2
            sel = np.ix_(gb == ids[0], gb == ids[1])
            self._thr[sel] = -depth
            self._thr[sel[::-1]] = -depth
        self._check = check
        self.sweep_radii = self._compute_sweep_radii(mask)

    def _compute_sweep_radii(self, mask: np.ndarray) -> np.ndarray:
        """[dof] m: r_i bounds the distance of any collidable robot/held point from joint i's axis, so a
        joint step Δq moves no such point by more than Σ_i r_i |Δq_i| (slide joints: r_i = 1).

        Configuration independent: anchor→body origin <= |jnt_pos| + Σ |body_pos| along the chain, plus
        each geom's |geom_pos| + bounding radius; the held object extends the TCP body.
        """
        m = self.model
        ext = np.full(m.nbody, -np.inf)          # farthest collidable geom surface from the body origin
        for g in np.flatnonzero(self._collidable):
            b = int(m.geom_bodyid[g])
            ext[b] = max(ext[b], float(np.linalg.norm(m.geom_pos[g]) + m.geom_rbound[g]))
        if self._attached is not None:
            obj, _, T = self._attached
            tcp_body = int(m.site_bodyid[self._tcp_site_id])
            reach = float(np.linalg.norm(m.site_pos[self._tcp_site_id]) + np.linalg.norm(T[:3, 3]))
            ext[tcp_body] = max(ext[tcp_body], reach + max(0.0, float(ext[obj])))
        body_len = np.linalg.norm(m.body_pos, axis=1)
        # joints move their body's origin relative to the parent: a hinge with an offset anchor by up to
        # 2 |jnt_pos|, a slide joint by its travel
        for j in range(m.njnt):
            if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE):
                travel = float(np.max(np.abs(m.jnt_range[j]))) if m.jnt_limited[j] else 1.0
                body_len[m.jnt_bodyid[j]] += travel
            elif int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_HINGE):
                body_len[m.jnt_bodyid[j]] += 2.0 * float(np.linalg.norm(m.jnt_pos[j]))
        r = np.zeros(self.dof)
        for i, j in enumerate(self.joint_ids):
            if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE):
                r[i] = 1.0
                continue
            jb = int(m.jnt_bodyid[j])
            best = 0.0
            for b in range(m.nbody):
                if not (mask[b] >> i) & 1 or not np.isfinite(ext[b]):
                    continue
                if self._attached is not None and b == self._attached[0]:
                    continue            # accounted for at the TCP body
                chain, k = 0.0, b
                while k != jb and k != 0:
                    chain += body_len[k]
                    k = int(m.body_parentid[k])
                best = max(best, chain + ext[b])
            r[i] = float(np.linalg.norm(m.jnt_pos[j])) + best
        return r

    def allow(self, body_a: str, body_b: str, penetration: float | None = None) -> None:
        """Exempt contacts between two bodies from now on.

        penetration: None ignores the pair entirely (e.g. the held object and the surface it leaves);
        a depth p >= 0 (m) only waives the margin: the bodies may touch, but a contact penetrating deeper
        than p still counts (fingers closing around the target must not land on it).
        """
        pair = frozenset((self._body_id(body_a), self._body_id(body_b)))
        if penetration is None:
            self._ignored.add(pair)
        else:
            if not penetration >= 0:
                raise ValueError(f"penetration must be >= 0, got {penetration}")
            self._touching[pair] = float(penetration)
        self._rebuild_pair_mask()

    def set_clearance(self, clearance: dict[str, float]) -> None:
        """Replace the per-body clearances: robot (and held-object) contacts with these static bodies count
        when closer than max(margin, clearance[body]) m instead of margin. For objects whose twin pose is
        uncertain (reconstruction error): free motions keep a wider berth. `allow` exceptions still apply;
        a held body is moving and not affected. `{}` restores the plain margin."""
        new = {self._body_id(n): float(c) for n, c in clearance.items()}
        if any(c < 0 for c in new.values()):
            raise ValueError("clearances must be >= 0")
        if new != self._clearance:
            self._clearance = new
            self._rebuild_pair_mask()

    def disallow(self, body_a: str, body_b: str) -> None:
        """Undo `allow` (contacts between the two bodies count again with the full margin)."""
        pair = frozenset((self._body_id(body_a), self._body_id(body_b)))
        self._ignored.discard(pair)
        self._touching.pop(pair, None)
        self._rebuild_pair_mask()

    def attach(self, body_name: str, T_tcp_obj: np.ndarray) -> None:
        """Carry free body `body_name` rigidly with the TCP site at `T_tcp_obj` (4×4, object → TCP frame, m).

        Its contacts with the hand/fingers are ignored; with everything else they are checked.
        """
        m = self.model
        if self._tcp_site_id < 0:
            raise ValueError(f"attach needs a TCP site named {self.tcp_site!r} in the model")
        b = self._body_id(body_name)
        jnts = [j for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
                if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)]
        if m.body_jntnum[b] < 1 or not jnts:
            raise ValueError(f"body {body_name!r} has no free joint; only free bodies can be attached")
        T = np.asarray(T_tcp_obj, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"T_tcp_obj must be 4x4, got {T.shape}")
        self.detach()   # one held object at a time; the previous one returns to its world pose
        self._attached = (b, int(m.jnt_qposadr[jnts[0]]), T.copy())
        self._pos_rel = np.ascontiguousarray(T[:3, 3], dtype=np.float64)
        self._quat_rel = np.zeros(4)
        mujoco.mju_mat2Quat(self._quat_rel, np.ascontiguousarray(T[:3, :3]).ravel())
        self._quat_tcp, self._quat_obj, self._pos_obj = np.zeros(4), np.zeros(4), np.zeros(3)
        self._rebuild_pair_mask()

    def detach(self) -> None:
        """Stop carrying the attached body; it returns to its frozen world pose."""
        if self._attached is not None:
            adr = self._attached[1]
            self.data.qpos[adr:adr + 7] = self._qpos_world[adr:adr + 7]
        self._attached = None
        self._rebuild_pair_mask()

    @property
    def attached_body(self) -> str | None:
        if self._attached is None:
            return None
        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, self._attached[0])

    # ---- queries -----------------------------------------------------------------------------------
    def _contacts(self, q: np.ndarray) -> np.ndarray:
        """Set q, run kinematics + collision; return the [K,2] geom pairs that count as collisions."""
        m, d = self.model, self.data
        if self._qpos_slice is not None:
            d.qpos[self._qpos_slice] = q
        else:
            d.qpos[self.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        if self._attached is not None:
            # T_world_obj = T_world_tcp @ T_tcp_obj, written into the object's free-joint qpos
            adr, sid = self._attached[1], self._tcp_site_id
            xmat = d.site_xmat[sid]
            mujoco.mju_mat2Quat(self._quat_tcp, xmat)
            mujoco.mju_mulQuat(self._quat_obj, self._quat_tcp, self._quat_rel)
            mujoco.mju_rotVecQuat(self._pos_obj, self._pos_rel, self._quat_tcp)
            d.qpos[adr:adr + 3] = self._pos_obj + d.site_xpos[sid]
            d.qpos[adr + 3:adr + 7] = self._quat_obj
            mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        n = d.ncon
        if n == 0:
            return _NO_PAIRS
        g = d.contact.geom[:n]
        dist = d.contact.dist[:n]
        ok = (g[:, 0] >= 0) & (g[:, 1] >= 0)
        g, dist = g[ok], dist[ok]
        hit = self._check[g[:, 0], g[:, 1]] & (dist < self._thr[g[:, 0], g[:, 1]])
        return g[hit]

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> bool:
        for v, lo, hi in zip(q, self._lower_list, self._upper_list):
            if v < lo - tol or v > hi + tol:
                return False
        return True

    def limit_violation(self, q: np.ndarray, tol: float = 1e-9) -> str | None:
        """Human-readable description of the first joint-limit violation, or None."""
        q = np.asarray(q, dtype=float)
        for i in range(self.dof):
            if not (self.lower[i] - tol <= q[i] <= self.upper[i] + tol):
                return (f"joint {self.joint_names[i]} = {q[i]:.4f} outside its limits "
                        f"[{self.lower[i]:.4f}, {self.upper[i]:.4f}]")
        return None

    def is_valid(self, q: np.ndarray) -> bool:
        """True iff q ([dof], rad) is within the joint limits and no counted contact is closer than margin."""
        q = np.asarray(q, dtype=float)
        if not self.within_limits(q):
            return False
        return len(self._contacts(q)) == 0

    def collision_free(self, q: np.ndarray) -> bool:
        """Like `is_valid` without the joint-limit test (for samplers that respect the bounds already)."""
        return len(self._contacts(q)) == 0

    def first_collision(self, q: np.ndarray) -> tuple[str, str] | None:
        """Labels of the closest counted colliding geom pair at q (for messages), or None if collision-free."""
        pairs = self._contacts(np.asarray(q, dtype=float))
        if len(pairs) == 0:
            return None
        # report the deepest pair: re-derive its distance from the contact list
        d = self.data
        n = d.ncon
        best, best_dist = pairs[0], math.inf
        for k in range(n):
            g = d.contact.geom[k]
            if (g[0] >= 0 and g[1] >= 0 and self._check[g[0], g[1]] and d.contact.dist[k] < self._thr[g[0], g[1]]
                    and d.contact.dist[k] < best_dist):
                best, best_dist = g, float(d.contact.dist[k])
        return _geom_label(self.model, int(best[0])), _geom_label(self.model, int(best[1]))

    def path_is_valid(self, path: np.ndarray, resolution: float | None = 0.0005,
                      max_sweep: float | None = None) -> bool:
        """Dense re-check of a piecewise-linear joint path [M, dof]: every sample must be valid.

        Sampling per segment (the finer of the two when both are given):
          resolution: rad, joint-space L-inf step between samples.
          max_sweep: m, bound on how far any robot (or held-object) point moves between samples, from
            `sweep_radii` (|Δx| <= Σ_i r_i |Δq_i|). With max_sweep <= margin, every sample clear by
            `margin` certifies that the continuous motion stays clear by margin - max_sweep >= 0 against
            the world (for MuJoCo's collision geometry).
        """
        return self.first_invalid_segment(path, resolution, max_sweep) is None

    def segment_steps(self, qa: np.ndarray, qb: np.ndarray, resolution: float | None = 0.0005,
                      max_sweep: float | None = None) -> int:
        """Number of sub-steps used to check the straight segment qa→qb (see `path_is_valid`)."""
        dq = np.abs(np.asarray(qb, dtype=float) - np.asarray(qa, dtype=float))
        k = 1
        if resolution is not None:
            k = max(k, int(math.ceil(float(dq.max()) / resolution)))
        if max_sweep is not None:
            k = max(k, int(math.ceil(float(self.sweep_radii @ dq) / max_sweep)))
        return k

    def first_invalid_segment(self, path: np.ndarray, resolution: float | None = 0.0005,
                              max_sweep: float | None = None) -> int | None:
        """Index i of the first segment path[i]→path[i+1] with an invalid sample (-1: a lone waypoint)."""
        path = np.atleast_2d(np.asarray(path, dtype=float))
        if path.shape[1] != self.dof:
            raise ValueError(f"path must be [M,{self.dof}], got {path.shape}")
        if resolution is None and max_sweep is None:
            raise ValueError("give resolution and/or max_sweep")
        if (resolution is not None and resolution <= 0) or (max_sweep is not None and max_sweep <= 0):
            raise ValueError("resolution and max_sweep must be > 0")
        if len(path) == 1:
            return None if self.is_valid(path[0]) else -1
        for i, q in enumerate(path):  # limits are a box: linear segments between valid waypoints stay inside
            if not self.within_limits(q):
                return max(i - 1, 0)
        for i in range(len(path) - 1):
            a, b = path[i], path[i + 1]
            k = self.segment_steps(a, b, resolution, max_sweep)
            # coarse-to-fine order: a collision in the middle of a long segment is found after a few checks
            for j in _coarse_to_fine(k + 1):
                if i and j == 0:
                    continue            # checked as the previous segment's end
                if len(self._contacts(a + (j / k) * (b - a))):
                    return i
        return None


def _coarse_to_fine(n: int) -> np.ndarray:
    """Indices 0..n-1 ordered by decreasing stride (endpoints first), each exactly once."""
    order = [0, n - 1] if n > 1 else [0]
    seen = np.zeros(n, dtype=bool)
    seen[order] = True
    stride = 1 << max(0, (n - 1).bit_length() - 1)
    while stride >= 1:
        idx = np.arange(0, n, stride)
        idx = idx[~seen[idx]]
        seen[idx] = True
        order.extend(idx.tolist())
        stride //= 2
    return np.asarray(order)


def interpolate_path(path: np.ndarray, resolution: float) -> np.ndarray:
    """Resample a piecewise-linear path [M,n] with L-inf steps <= resolution; keeps all waypoints. [K,n]."""
    path = np.atleast_2d(np.asarray(path, dtype=float))
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        k = max(1, int(math.ceil(np.max(np.abs(b - a)) / resolution)))
        s = np.arange(1, k + 1)[:, None] / k
        out.append(a + s * (b - a))
    return np.concatenate(out, axis=0)


# ---- OMPL planning --------------------------------------------------------------------------------

def _ompl():
    from ompl import base as ob, geometric as og, util as ou
    return ob, og, ou


def _seed_ompl(seed: int) -> None:
    ob, og, ou = _ompl()
    # setSeed warns once sampling has started; the seed still governs every RNG created afterwards
    # (each plan_path call builds fresh planners/samplers), which is what makes runs reproducible.
    ou.setLogLevel(ou.LOG_NONE)
    ou.RNG.setSeed(int(seed) % (2**31 - 1) + 1)
    ou.setLogLevel(ou.LOG_WARN)


def _describe_invalid(checker: CollisionChecker, q: np.ndarray, what: str) -> str | None:
    lim = checker.limit_violation(q)
    if lim is not None:
        return f"{what} configuration violates a joint limit: {lim}"
    pair = checker.first_collision(q)
    if pair is not None:
        return (f"{what} configuration in collision (closer than the {checker.margin * 1000:.1f} mm margin): "
                f"{pair[0]} with {pair[1]}")
    return None


def _straight_blocker(checker: CollisionChecker, q_start: np.ndarray, q_goal: np.ndarray) -> str:
    """'A with B' for the first colliding pair along the straight joint-space line (for messages)."""
    k = checker.segment_steps(q_start, q_goal, None, max(0.5 * checker.margin, 0.001))
    for j in range(k + 1):
        pair = checker.first_collision(q_start + (j / k) * (q_goal - q_start))
        if pair is not None:
            return f"{pair[0]} with {pair[1]}"
    return "nothing at this sampling"


PLAN_CHECKS = 20000   # state validity checks one planning query may spend (~1 s on 2 cores at ~20k checks/s)


def _ompl_solve(checker: CollisionChecker, q_start: np.ndarray, q_goal: np.ndarray, time_limit: float,
                planner: str, resolution: float, simplify: bool,
                max_checks: int | None = None) -> tuple[np.ndarray | None, int]:
    """One OMPL query: (the path, or None when none was found before `max_checks` validity checks (when
    given) or `time_limit` s, whichever came first; the number of validity checks made)."""
    ob, og, ou = _ompl()
    ou.setLogLevel(ou.LOG_ERROR)
    n = checker.dof
    space = ob.RealVectorStateSpace(n)
    bounds = ob.RealVectorBounds(n)
    for i in range(n):
        bounds.setLow(i, float(checker.lower[i]))
        bounds.setHigh(i, float(checker.upper[i]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    idx = range(n)
    q_buf = np.empty(n)

    n_checks = [0]

    def valid(state) -> bool:
        n_checks[0] += 1
        for i in idx:
            q_buf[i] = state[i]
        return checker.collision_free(q_buf)

    ss.setStateValidityChecker(valid)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution)
    start, goal = space.allocState(), space.allocState()
    for i in idx:
        start[i] = float(q_start[i])
        goal[i] = float(q_goal[i])
    ss.setStartAndGoalStates(start, goal)
    ss.setPlanner(getattr(og, planner)(si))
    if max_checks is None:
        status = ss.solve(float(time_limit))
    else:
        # a budget of work, not of wall time: a seeded query ends the same way on a loaded machine (a wall-clock
        # limit made "no path" depend on the load, and with it the fallback without object clearance)
        t_end = time.perf_counter() + float(time_limit)
        ptc = ob.PlannerTerminationCondition(lambda: n_checks[0] >= max_checks or time.perf_counter() >= t_end)
        status = ss.solve(ptc)
        del ptc
    if not ss.haveExactSolutionPath():
        return None, n_checks[0]
    p = ss.getSolutionPath()
    if simplify:
        # vertex reduction + rope shortcutting: on Panda pick-and-place motions as short as the full
        # `simplifySolution` (which adds B-spline smoothing passes) at ~5x less time
        ps = og.PathSimplifier(si)
        ps.reduceVertices(p)
        ps.ropeShortcutPath(p)
    out = np.array([[p.getState(k)[i] for i in idx] for k in range(p.getStateCount())])
    del status, ss, si, space
    out[0], out[-1] = q_start, q_goal  # exact endpoints (OMPL copies, but be explicit)
    return out, n_checks[0]


def shortcut(checker: CollisionChecker, path: np.ndarray, resolution: float | None = 0.0005,
             iterations: int = 60, seed: int | None = None, max_sweep: float | None = None) -> np.ndarray:
    """Random shortcutting with dense checks: replace path[i..j] by a straight segment when it is valid.

    OMPL's simplifier only checks at the planner's (coarse) resolution; this pass checks every candidate
    segment densely (`path_is_valid` sampling), so it never introduces a clip. Endpoints are kept exactly.
    """
    rng = np.random.default_rng(seed)
    path = np.asarray(path, dtype=float).copy()
    for _ in range(iterations):
        if len(path) <= 2:
            break
        # shortcut between random points on two different segments (partial shortcutting)
        a, b = sorted(rng.choice(len(path) - 1, size=2, replace=False))
        if b - a < 1:
            continue
        ta, tb = rng.random(), rng.random()
        qa = path[a] + ta * (path[a + 1] - path[a])
        qb = path[b] + tb * (path[b + 1] - path[b])
        if checker.path_is_valid(np.stack([qa, qb]), resolution, max_sweep):
            new = np.concatenate([path[:a + 1], qa[None], qb[None], path[b + 1:]])
            if _length(new) < _length(path) - 1e-6:
                path = _dedupe(new)
    return path


def _length(path: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))


def _dedupe(path: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    keep = [0] + [k for k in range(1, len(path)) if np.max(np.abs(path[k] - path[k - 1])) > tol]
    out = path[keep]
    if len(out) == 1:
        out = np.stack([path[0], path[-1]])
    return out


def plan_path(checker: CollisionChecker, q_start: np.ndarray, q_goal: np.ndarray, time_limit: float = 1.0,
              planner: str = "RRTConnect", resolution: float = 0.002, seed: int | None = None,
              simplify: bool = True, check_resolution: float | None = None, max_sweep: float | None = None,
              retries: int = 2, shortcut_iters: int = 0, max_checks: int | None = None) -> np.ndarray:
    """Collision-free joint path from q_start to q_goal, [M, dof] rad, endpoints exact.

    Args:
        checker: validity of configurations (its attached object / allowed pairs apply).
        time_limit: s, per OMPL attempt (with max_checks: a cap against a stuck query only).
        max_checks: state validity checks per OMPL attempt (e.g. PLAN_CHECKS); the attempt ends when they are
            spent: with a seed, the same result however loaded the machine is (None: time_limit alone).
        planner: one of `PLANNERS`.
        resolution: OMPL state-validity checking resolution, as a fraction of the joint space's extent
            (OMPL's convention; the Panda's extent is ~13 rad, so 0.002 ≈ 0.026 rad steps). Coarse is
            fast; the straight line and the final path are re-checked densely anyway.
        seed: seeds OMPL's RNG and the shortcutter: same seed, same world → same path.
        simplify: OMPL's path simplifier (vertex reduction + rope shortcutting, coarse checks).
        check_resolution, max_sweep: sampling of the dense re-check (see `CollisionChecker.path_is_valid`).
            Default: max_sweep = margin / 2 (at least 1 mm), so a path that passes stays clear of the world
            by at least half the margin along the whole continuous motion.
        retries: OMPL re-plans with 4× finer resolution when the dense re-check fails.
        shortcut_iters: extra random partial shortcuts checked densely after OMPL's simplifier (each
            successful one costs a dense segment check, so off by default).

    Raises:
        PlanningError: start/goal invalid (names the joint or the geom pair), or no path in time.
    """
    q_start = np.asarray(q_start, dtype=float).reshape(-1)
    q_goal = np.asarray(q_goal, dtype=float).reshape(-1)
    if q_start.shape != (checker.dof,) or q_goal.shape != (checker.dof,):
        raise ValueError(f"q_start/q_goal must have {checker.dof} values, got {q_start.shape}, {q_goal.shape}")
    if planner not in PLANNERS:
        raise ValueError(f"unknown planner {planner!r}; choose from {', '.join(PLANNERS)}")
    _, og, _ = _ompl()
    if not hasattr(og, planner):
        raise ValueError(f"planner {planner!r} is not in this OMPL build")
    if check_resolution is None and max_sweep is None:
        max_sweep = max(0.5 * checker.margin, 0.001)
    dense = dict(resolution=check_resolution, max_sweep=max_sweep)
    for q, what in ((q_start, "start"), (q_goal, "goal")):
        msg = _describe_invalid(checker, q, what)
        if msg is not None:
            raise PlanningError(msg)
    # many motions are free in a straight line: check it densely before calling the planner
    straight = np.stack([q_start, q_goal])
    if checker.path_is_valid(straight, **dense):
        return straight
    if seed is not None:
        _seed_ompl(seed)
    res = resolution
    t0 = time.perf_counter()
    for attempt in range(retries + 1):
        t_try = time.perf_counter()
        path, spent = _ompl_solve(checker, q_start, q_goal, time_limit, planner, res, simplify, max_checks)
        if path is None:
            budget = (f"{time_limit:.2f} s" if max_checks is None or spent < max_checks else
                      f"{max_checks} collision checks ({time.perf_counter() - t_try:.2f} s)")
            raise PlanningError(
                f"{planner} found no collision-free path in {budget} "
                f"(start {np.round(q_start, 3).tolist()}, goal {np.round(q_goal, 3).tolist()}; "
                f"the straight line is blocked by {_straight_blocker(checker, q_start, q_goal)})")
        if simplify and shortcut_iters > 0:
            path = shortcut(checker, path, iterations=shortcut_iters,
                            seed=None if seed is None else seed + attempt, **dense)
        if checker.path_is_valid(path, **dense):
            path[0], path[-1] = q_start, q_goal
            return path
        res /= 4.0  # the coarse OMPL check let a thin obstacle through: plan again, more finely
    raise PlanningError(
        f"no path passed the dense re-check after {retries + 1} attempts "
        f"({time.perf_counter() - t0:.2f} s); last OMPL resolution {res * 4:.2e}")
