"""The program for a real arm: the validated timeline cut at its gripper commands into blocking phases.

The whole-timeline files (trajectory.*, gripper.ros2.yaml) give the gripper the holds the simulated hand
needed (execute.CLOSE_TIME 0.6 s, OPEN_TIME 0.4 s); a real Franka Hand at the exported speed (0.05 m/s) takes
longer (80 -> 27 mm: ~1.1 s), and its Grasp / Move goals are separate actions that nothing synchronises with a
FollowJointTrajectory goal. The program makes the arm wait for the hand instead:

    program.json                         the phases in order: kind (arm | gripper), file, start state,
                                         duration, where the phase sits in the validated timeline
    program/NN_arm.goal.ros2.yaml        control_msgs/action/FollowJointTrajectory goal of one arm phase:
                                         the motions (with their settle holds) between two gripper
                                         actions, time_from_start from 0; starts and ends at rest
    program/NN_gripper_grasp.goal.ros2.yaml   franka_msgs/action/Grasp goal (width, epsilon, speed, force)
    program/NN_gripper_move.goal.ros2.yaml    franka_msgs/action/Move goal (width, speed)

Run the phases in order, each when the one before has *finished* (its action result received); stop on a
failed result (a Grasp whose final width is outside width - epsilon.inner .. width + epsilon.outer: the
object is missing or another size). A gripper phase replaces the hold the simulated hand closed / opened
in (its `simulated_duration_s`); the arm stands still at the phase's `q` meanwhile. So the arm phases laid
end to end with each gripper phase as a stand-still of its simulated duration give the validated timeline
(`timeline`), which is how the tests check it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.io import write_json, write_text
from splattwin.robot.trajectory import UNITS, GripperCommand, Trajectory, concatenate

__all__ = ["Phase", "build_phases", "timeline", "write_program", "PROGRAM_JSON", "PROGRAM_DIR", "PROGRAM_FILE"]

PROGRAM_JSON = "program.json"
PROGRAM_DIR = "program"
PROGRAM_FILE = re.compile(r"^\d{2,}_(arm|gripper_grasp|gripper_move)\.goal\.ros2\.yaml$")  # what we write there
FORMAT = "splattwin.program"
VERSION = 1
REST_TOL = 1e-6          # rad/s: an arm phase starts and ends with every joint velocity below this
STILL_TOL = 1e-9         # rad: a segment whose joints move less than this is a stand-still (a gripper hold)
_ACTIONS = {"grasp": ("franka_msgs/action/Grasp", "grasp", "gripper_grasp"),
            "open": ("franka_msgs/action/Move", "move", "gripper_move")}


@dataclass
class Phase:
    """One step of the program. kind "arm": `trajectory` (time from 0, no gripper commands) made of the
    segments `labels`; kind "gripper": `command` (issued at the start of the phase), the arm held at
    q_start; `duration` the simulated hold (0 when the validated run issued it as a motion began).
    t_start: where the phase begins in the validated timeline (s)."""

    kind: str
    t_start: float
    duration: float
    q_start: np.ndarray
    q_end: np.ndarray
    labels: list[str] = field(default_factory=list)
    trajectory: Trajectory | None = None
    command: GripperCommand | None = None


def _still(tr: Trajectory) -> bool:
    return bool(np.ptp(tr.q, axis=0).max(initial=0.0) <= STILL_TOL and np.abs(tr.qd).max(initial=0.0) <= REST_TOL)


def build_phases(segments: list[tuple[str, Trajectory]]) -> list[Phase]:
    """The program's phases of the executed segments (label, trajectory; in order, as `concatenate` lays
    them end to end). A gripper command starts a gripper phase: a stand-still segment carrying it (the
    close / open hold) becomes that phase, a motion carrying it (the first transit's open) is preceded
    by a gripper phase of 0 s. The segments between gripper phases form one arm phase. ValueError when
    a gripper command lies inside a motion or an arm phase does not start and end at rest."""
    phases: list[Phase] = []
    pending: list[tuple[str, Trajectory]] = []
    t = 0.0
    pending_t = 0.0

    def flush() -> None:
        if not pending:
            return
        tr = concatenate([Trajectory(s.t, s.q, s.qd, s.qdd, s.joint_names) for _, s in pending])
        tr = tr.with_velocity_accelerations()
        tr.meta = {}
        labels = [lab for lab, _ in pending]
        for where, k in (("start", 0), ("end", -1)):
            v = float(np.abs(tr.qd[k]).max())
            if v > REST_TOL:
                raise ValueError(f"the arm phase of {', '.join(labels)} does not {where} at rest "
                                 f"(|qd| {v:.3g} rad/s): it cannot wait for a gripper action there")
        phases.append(Phase("arm", pending_t, tr.duration, tr.q[0].copy(), tr.q[-1].copy(), labels, tr))
        pending.clear()

    for label, seg in segments:
        if not len(seg):
            continue
        t0 = float(seg.t[0])
        for g in seg.gripper:
            if abs(g.t - t0) > 1e-9:
                raise ValueError(f"gripper command {g.command!r} {g.t - t0:.3f} s into segment {label!r}: "
                                 "a program issues gripper actions only between arm motions")
        if seg.gripper:
            flush()
            still = _still(seg)
            for k, g in enumerate(seg.gripper):
                last = k == len(seg.gripper) - 1
                dur = seg.duration if still and last else 0.0
                phases.append(Phase("gripper", t, dur, seg.q[0].copy(), seg.q[0].copy(),
                                    [label] if still and last else [], command=g.shifted(t - g.t)))
            if still:
                t += seg.duration
                pending_t = t
                continue
        if not pending:
            pending_t = t
        pending.append((label, seg))
        t += seg.duration
    flush()
    for a, b in zip(phases, phases[1:]):
        jump = float(np.abs(b.q_start - a.q_end).max())
        if jump > 1e-6:
            raise ValueError(f"a program phase starts {jump:.3g} rad from where the one before ends")
    return phases


def timeline(phases: list[Phase], dt: float = 0.01) -> Trajectory:
    """The program played as the validation ran it: the arm phases end to end, each gripper phase a
    stand-still of its simulated duration (with its command at its start)."""
    parts = []
    names = next((x.trajectory.joint_names for x in phases if x.kind == "arm"), None)
    for p in phases:
        if p.kind == "arm":
            parts.append(p.trajectory)
        else:
            h = Trajectory.hold(p.q_start, p.duration, dt, names) if p.duration > 0 else \
                Trajectory(np.zeros(1), p.q_start[None], np.zeros((1, len(p.q_start))),
                           np.zeros((1, len(p.q_start))), names)
            h.gripper = [p.command.shifted(-p.command.t)]
            parts.append(h)
    return concatenate(parts)


def _gripper_expected_s(prev_width: float | None, g: GripperCommand) -> float | None:
    """s the real hand needs to move its fingers at the command's speed (without the force build-up)."""
    if prev_width is None or not g.speed:
        return None
    return round(abs(prev_width - g.width) / g.speed, 3)


def write_program(out: str | Path, segments: list[tuple[str, Trajectory]], meta: dict | None = None,
                  controller: str = "CONTROLLER", gripper_ns: str = "franka_gripper") -> dict[str, Path]:
    """OUT/program.json and OUT/program/NN_*.goal.ros2.yaml of the executed segments (exported names).
    ValueError (nothing written) when they do not cut into a program (`build_phases`)."""
    out = Path(out)
    phases = build_phases(segments)
    if not phases or not any(p.kind == "arm" for p in phases):
        raise ValueError("no arm motion to run")
    names = next(p.trajectory.joint_names for p in phases if p.kind == "arm")
    paths: dict[str, Path] = {}
    docs = []
    width: float | None = None
    n = len(phases)
    for i, p in enumerate(phases):
        nn = f"{i:02d}"
        prev = f"phase {i - 1:02d} has finished (its result received)" if i else "the arm is at `start.q`"
        if p.kind == "arm":
            rel = f"{PROGRAM_DIR}/{nn}_arm.goal.ros2.yaml"
            paths[f"program:{nn}"] = p.trajectory.save_ros2_goal_yaml(
                out / rel, controller=controller,
                note=f"phase {nn} of {n} in ../{PROGRAM_JSON}: send when {prev}; starts and ends at rest")
            docs.append({"index": i, "kind": "arm", "action": "control_msgs/action/FollowJointTrajectory",
                         "file": rel, "segments": p.labels, "duration_s": round(p.duration, 6),
                         "samples": len(p.trajectory), "start_q": p.q_start.tolist(), "end_q": p.q_end.tolist(),
                         "timeline_start_s": round(p.t_start, 6)})
            continue
        g = p.command
        action, verb, stem = _ACTIONS[g.command]
        rel = f"{PROGRAM_DIR}/{nn}_{stem}.goal.ros2.yaml"
        goal = g.ros2_goal()["goal"]
        head = (f"# {action} goal (width m, speed m/s" + (", epsilon m, force N" if g.command == "grasp" else "")
                + f"); phase {nn} of {n} in ../{PROGRAM_JSON}: send when {prev}, wait for its result before "
                "the next phase (a failed result: stop)\n"
                f"# ros2 action send_goal /{gripper_ns}/{verb} {action} \"$(cat {Path(rel).name})\"\n")
        paths[f"program:{nn}"] = write_text(out / rel, head + _yaml(goal))
        doc = {"index": i, "kind": "gripper", "action": action, "command": g.command, "file": rel, "goal": goal,
               "blocking": True, "q": p.q_start.tolist(), "simulated_duration_s": round(p.duration, 6),
               "real_finger_motion_s": _gripper_expected_s(width, g), "timeline_start_s": round(p.t_start, 6)}
        if g.planned_width is not None:
            doc["planned_width"] = g.planned_width
        docs.append(doc)
        width = g.width
    first = phases[0]
    grip0 = first.command.command if first.kind == "gripper" else None
    doc = {"format": FORMAT, "version": VERSION, "units": dict(UNITS), **(meta or {}),
           "joint_names": list(names),
           "how_to_run": ("run the phases in order, each when the one before has finished (its action result "
                          "received): arm phases as FollowJointTrajectory goals (each starts and ends at rest, "
                          "time_from_start from 0), gripper phases as franka_msgs Grasp / Move goals, blocking; "
                          "stop on a failed result. Bring the arm to start.q first."),
           "start": {"q": first.q_start.tolist(), "gripper": grip0},
           "validated_duration_s": round(sum(p.duration for p in phases), 6),
           "phases": docs}
    paths["program"] = write_json(out / PROGRAM_JSON, doc)
    return paths


def _yaml(doc: dict) -> str:
    import yaml

    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=1 << 16)
