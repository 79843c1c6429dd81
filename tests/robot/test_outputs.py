"""robot/results.json records the twin it was made on (`twin_digest`), so results of an earlier twin are
told apart (`results_twin`): the report shows none and the pipeline removes them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from splattwin.robot.outputs import results_twin, twin_digest


def small_twin(folder: Path, name: str = "cake", size: float = 0.1) -> Path:
    """A metric twin.json with one usable object and its collision mesh (no splats)."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import Background, Manifest, ObjectEntry

    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / "objects" / name / "collision.obj"
    mesh.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[size] * 3).export(mesh)
    Manifest(frame=TwinFrame("known_poses", scaled=True),
             objects=[ObjectEntry(name=name, label=1, usable=True, bbox_extent=[size] * 3,
                                  collision_mesh=f"objects/{name}/collision.obj",
                                  convex_parts=[f"objects/{name}/collision.obj"])],
             background=Background(table_extent=[-0.5, 0.5, -0.5, 0.5])).save(folder)
    return folder


def test_twin_digest_follows_the_objects_and_meshes_not_the_timings(tmp_path):
    from splattwin.twin.manifest import Manifest

    twin = small_twin(tmp_path / "t")
    d0 = twin_digest(twin)
    assert d0 is not None and d0 == twin_digest(twin)
    man = Manifest.load(twin)            # a deterministic rebuild: other run times, exports, build options
    man.timings["geometry"] = 12.3
    man.exports = {}
    man.config["build"] = {"splat": {"iters": 7}}
    man.save(twin)
    assert twin_digest(twin) == d0
    small_twin(twin, size=0.2)           # other meshes, same names
    assert twin_digest(twin) != d0
    other = small_twin(tmp_path / "o", name="dessert")
    assert twin_digest(other) != twin_digest(small_twin(tmp_path / "c"))
    assert twin_digest(tmp_path / "none") is None


def test_results_twin_says_why_results_are_not_this_twins(tmp_path):
    twin = small_twin(tmp_path / "t")
    assert results_twin({"twin_digest": twin_digest(twin), "nominal": {}}, twin) is None
    assert "earlier state of this twin" in results_twin({"twin_digest": "0" * 64}, twin)
    assert "no twin digest" in results_twin({"nominal": {}}, twin)     # an earlier splattwin's results
    assert "unreadable" in results_twin(None, twin)


def test_stale_results_says_a_missing_results_json_is_an_unfinished_run(tmp_path):
    """robot/ without results.json (written last: a plan stopped or killed) was reported as "results.json is
    unreadable" by `render`; it says what happened now."""
    from splattwin.robot.outputs import stale_results

    twin = small_twin(tmp_path / "t")
    (twin / "robot").mkdir(exist_ok=True)
    assert "missing: the `splattwin plan` run that wrote robot/ did not finish" in stale_results(twin)
    (twin / "robot" / "results.json").write_text("{not json")
    assert "unreadable" in stale_results(twin)


def test_error_results_record_the_twin_too(tmp_path):
    """results.json of a task that could not run (an unscaled twin) is this twin's result too."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.robot.options import RobotOptions
    from splattwin.robot.stage import RobotInputs, run
    from splattwin.twin.manifest import Manifest

    twin = small_twin(tmp_path / "t")
    man = Manifest.load(twin)
    man.frame = TwinFrame("unscaled", scaled=False, nominal_metre=5.0)
    man.save(twin)
    res = run(RobotInputs(twin, twin / "robot"), RobotOptions(task="default"), progress=False, record_errors=True)
    doc = json.loads(res.results.read_text())
    assert "error" in doc and doc["twin_digest"] == twin_digest(twin)
    assert results_twin(doc, twin) is None


def test_export_names_default_to_the_real_robots_and_fit_the_arm():
    from splattwin.errors import InputError
    from splattwin.robot.export import export_names

    sim = [f"joint{i}" for i in range(1, 8)]
    n = export_names(None, sim, "link0", default_model=True)          # the Menagerie Panda
    assert n.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8)) and n.base_frame == "panda_link0"
    assert n.joint_map(sim)["panda_joint4"] == "joint4"
    n = export_names("fr3", sim, "link0", default_model=True)
    assert n.joint_names[0] == "fr3_joint1" and n.base_frame == "fr3_link0"
    n = export_names(None, ["a", "b"], "base", default_model=False)   # a user's MJCF keeps its names
    assert n.joint_names == ("a", "b") and n.base_frame == "base"
    assert export_names("x1, x2", ["a", "b"], "base", default_model=False).joint_names == ("x1", "x2")
    with pytest.raises(InputError, match="7 joints; this arm has 2"):
        export_names("panda", ["a", "b"], "base", default_model=False)
    with pytest.raises(InputError, match="gives 3 names"):
        export_names("x,y,z", ["a", "b"], "base", default_model=False)
    with pytest.raises(InputError, match="--joint-names"):
        export_names("bad name,x", ["a", "b"], "base", default_model=False)


def test_base_frame_named_for_any_joint_naming():
    """--base-frame names the base in the exported files, for a list of joint names (whose base was the MJCF's
    root body, unnameable before) and for the named robots; it must be a TF frame id."""
    from splattwin.errors import InputError
    from splattwin.robot.export import export_names
    from splattwin.robot.options import RobotOptions

    sim = [f"joint{i}" for i in range(1, 8)]
    custom = ",".join(f"arm_j{i}" for i in range(1, 8))
    assert export_names(custom, sim, "link0", default_model=True).base_frame == "link0"     # the root body
    n = export_names(custom, sim, "link0", default_model=True, base_frame="arm_base_link")
    assert n.base_frame == "arm_base_link" and n.joint_names[0] == "arm_j1"
    assert export_names("fr3", sim, "link0", True, base_frame="left/fr3_link0").base_frame == "left/fr3_link0"
    assert export_names("model", sim, "link0", True, base_frame="_base").base_frame == "_base"
    assert export_names(None, sim, "link0", True, base_frame=None).base_frame == "panda_link0"
    for bad in ("/base_link", "base link", "1base", "a//b", "base/", "", "base-link", "twin", "a" * 65):
        with pytest.raises(InputError, match="--base-frame"):
            export_names(custom, sim, "link0", default_model=True, base_frame=bad)
        with pytest.raises(InputError, match="--base-frame"):
            RobotOptions(joint_names=custom, base_frame=bad).validate()
    RobotOptions(joint_names=custom, base_frame="robot1/base_link").validate()


def test_base_transform_and_base_frame_moveit_scene(tmp_path):
    """robot/base_transform.yaml is T_twin_base as a TransformStamped (+ static_transform_publisher
    arguments), and the MoveIt files hold the twin's objects in the base frame."""
    import numpy as np
    import yaml

    from splattwin.robot.export import write_base_frame_moveit, write_base_transform
    from splattwin.transforms import invert_pose, pose_xyz_yaw
    from splattwin.twin.manifest import Manifest
    from splattwin.twin.moveit import parse_scene, pose_from_msg

    twin = small_twin(tmp_path / "t")
    T_twin_base = pose_xyz_yaw(-0.5, 0.1, 0.02, np.pi / 2)
    path = write_base_transform(tmp_path / "base_transform.yaml", T_twin_base, "panda_link0")
    text = path.read_text()
    doc = yaml.safe_load(text)
    assert doc["header"]["frame_id"] == "twin" and doc["child_frame_id"] == "panda_link0"
    tr, rot = doc["transform"]["translation"], doc["transform"]["rotation"]
    assert [tr[k] for k in "xyz"] == pytest.approx([-0.5, 0.1, 0.02])
    assert [rot[k] for k in "xyzw"] == pytest.approx([0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    assert ("static_transform_publisher --x -0.5 --y 0.1 --z 0.02 --qx 0 --qy 0 --qz 0.707106781 "
            "--qw 0.707106781 --frame-id twin --child-frame-id panda_link0") in text
    paths = write_base_frame_moveit(tmp_path / "robot", twin, T_twin_base, "panda_link0")
    msgs = yaml.safe_load(paths["moveit_collision_objects"].read_text())
    T_twin_obj = Manifest.load(twin).object("cake").pose
    cake = next(m for m in msgs if m["id"] == "cake")
    assert cake["header"]["frame_id"] == "panda_link0"
    np.testing.assert_allclose(pose_from_msg(cake["pose"]), invert_pose(T_twin_base) @ T_twin_obj, atol=1e-9)
    _, objs = parse_scene(paths["moveit_scene"].read_text())
    np.testing.assert_allclose(next(o for o in objs if o.id == "cake").T_world_obj,
                               invert_pose(T_twin_base) @ T_twin_obj, atol=1e-8)


def test_remove_previous_takes_the_robot_exports_too(tmp_path):
    """Stale or replaced results take their base transform, ROS goals and base-frame MoveIt scene with them
    (the pipeline and `plan` clear OUT with remove_previous); files of other names stay."""
    from splattwin.robot.outputs import remove_previous

    out = tmp_path / "robot"
    (out / "moveit").mkdir(parents=True)
    (out / "program").mkdir(parents=True)
    names = ["results.json", "base_transform.yaml", "trajectory.goal.ros2.yaml", "gripper.ros2.yaml",
             "moveit/collision_objects.yaml", "moveit/scene.scene", "moveit/mine.txt", "notes.txt", "program.json",
             "program/00_gripper_move.goal.ros2.yaml", "program/01_arm.goal.ros2.yaml",
             "program/12_gripper_grasp.goal.ros2.yaml", "program/mine.yaml"]
    for n in names:
        (out / n).write_text("x")
    remove_previous(out)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == ["moveit/mine.txt", "notes.txt",
                                                                                      "program/mine.yaml"]


def test_written_timeline_has_the_start_state_names_and_gripper(tmp_path):
    """write_trajectories: segments renamed to the exported joints, one timeline as long as the segments
    together, the gripper commands at their segments' starts, the start configuration and joint map."""
    import json

    import numpy as np

    from splattwin.robot.export import export_names
    from splattwin.robot.outputs import write_trajectories
    from splattwin.robot.trajectory import GripperCommand, Trajectory

    sim = [f"joint{i}" for i in range(1, 8)]
    q0 = np.full(7, 0.1)
    move = Trajectory(np.arange(4) * 0.01, q0 + np.arange(4)[:, None] * 0.01, np.zeros((4, 7)), np.zeros((4, 7)), sim,
                      [GripperCommand.open(0.0, 0.08)]).held_until(0.1006)
    close = Trajectory.hold(move.q[-1], 0.6, joint_names=sim)
    close.gripper = [GripperCommand.grasp(0.0, 0.05)]
    names = export_names(None, sim, "link0", default_model=True)
    paths, notes, real = write_trajectories(tmp_path, [("step1_transit", move), ("step1_close", close)],
                                            {"robot": "panda", "joint_map": names.joint_map(sim)}, names)
    assert notes == [] and (tmp_path / "segments" / "step1_close.json").is_file() and real["written"]
    doc = json.loads(paths["trajectory_json"].read_text())
    assert doc["joint_names"][0] == "panda_joint1" and doc["joint_map"]["panda_joint1"] == "joint1"
    assert doc["t"][-1] == pytest.approx(0.7006) and doc["start"]["q"] == pytest.approx(q0.tolist())
    assert doc["start"]["gripper"] == "open" and doc["sample_rate_hz"] == 100.0
    assert [(g["t"], g["command"]) for g in doc["gripper"]] == [(0.0, "open"), (pytest.approx(0.1006), "grasp")]
    seg = json.loads((tmp_path / "segments" / "step1_transit.json").read_text())
    assert seg["joint_names"][6] == "panda_joint7"
    for name in ("trajectory.csv", "trajectory.ros2.yaml", "trajectory.goal.ros2.yaml", "gripper.ros2.yaml"):
        assert (tmp_path / name).is_file()


def test_trial_failures_name_each_failed_trial_and_why():
    """`plan --trials 4 --sigma 0.03` printed 'overall: success', 'trials: 2/4' and exited 1, naming no trial."""
    from splattwin.robot.outputs import trial_failures

    ok = {"success": True, "seed": 1, "steps": [{"index": 1, "pick": "cube", "success": True}]}
    bad = {"success": False, "seed": 2, "steps": [{"index": 1, "pick": "hammer", "success": True},
                                                  {"index": 2, "pick": "cube", "success": False,
                                                   "failure": "'cube' not lifted with the gripper (rose 0.0 cm)"}]}
    died = {"success": False, "seed": 3, "steps": [], "error": "worker: killed"}
    assert trial_failures({"results": [ok, ok]}) == []
    lines = trial_failures({"results": [ok, bad, died]})
    assert lines == ["trial 2 (seed 2, trials/2.json) failed at step 2 (cube): 'cube' not lifted with the gripper "
                     "(rose 0.0 cm)", "trial 3 (seed 3) failed at its start: worker: killed"]
    many = trial_failures({"results": [bad] * 8}, limit=5)
    assert len(many) == 6 and many[-1].startswith("... and 3 more failed trial(s)")
