"""Playback cameras: capture cameras, user YAML, eye-in-hand, and the refusals (exit 2)."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.cli import main
from splattwin.errors import InputError
from splattwin.playback.cameras import (EyeInHand, capture_cameras, check_camera, load_camera_yaml,
                                        resolve_camera)
from splattwin.playback.scene import DynamicScene


def test_capture_and_user_cameras(tiny_twin, tmp_path):
    cams = capture_cameras(tiny_twin)
    assert [c.name for c in cams] == ["view_0", "view_1"]
    assert resolve_camera("view_1", tiny_twin).name == "view_1"
    assert resolve_camera("capture:0", tiny_twin, width=48).width == 48
    with pytest.raises(InputError, match="no capture camera"):
        resolve_camera("nope", tiny_twin)
    # --width reaches the wrist camera too (ignored before), its field of view kept
    wrist = resolve_camera("wrist", tiny_twin, width=320)
    assert isinstance(wrist, EyeInHand) and (wrist.width, wrist.height) == (320, 240)
    K0, K1 = EyeInHand().intrinsics(), wrist.intrinsics()
    assert K1[0, 0] / 320 == pytest.approx(K0[0, 0] / EyeInHand().width)
    for bad in ("capture:2", "capture:-1", "capture:x"):   # -1 rendered the last camera (a Python index)
        with pytest.raises(InputError, match=rf"no capture camera '{bad}' \(the twin has 2: 0..1\)"):
            resolve_camera(bad, tiny_twin)
    y = tmp_path / "cam.yaml"
    y.write_text("width: 200\nheight: 100\nfov_x_deg: 90\neye: [0.5, 0, 0.4]\nlook_at: [0, 0, 0]\n")
    c = load_camera_yaml(y)
    assert (c.width, c.height) == (200, 100)
    assert c.fx == pytest.approx(100.0)                 # 90 deg over 200 px
    z = c.T_world_cam[:3, 2]
    np.testing.assert_allclose(z, -np.array([0.5, 0, 0.4]) / np.linalg.norm([0.5, 0, 0.4]), atol=1e-9)
    h = tmp_path / "hand.yaml"
    h.write_text("frame: hand\nwidth: 64\nheight: 48\nfov_y_deg: 40\n")
    assert isinstance(load_camera_yaml(h), EyeInHand)


def test_eye_in_hand_default_is_d435_like_and_follows_the_hand():
    e = EyeInHand()
    K = e.intrinsics()
    assert (e.width, e.height) == (640, 480)
    fov_y = 2 * np.degrees(np.arctan(240 / K[1, 1]))
    assert fov_y == pytest.approx(42.5)
    assert K[0, 0] == pytest.approx(K[1, 1])
    T = np.eye(4)
    T[:3, 3] = [0.3, 0.1, 0.4]
    cam = e.camera(T)
    np.testing.assert_allclose(cam.T_world_cam, T @ e.T_hand_cam)
    # it looks along the approach axis (hand +z), towards the fingertips
    assert cam.T_world_cam[:3, 2] @ T[:3, 2] > 0.9


@pytest.mark.parametrize("bad,msg", [("eye: [0, 0, 1]\n", "pose missing"),
                                     ("eye: [0, 0, 1]\nlook_at: [0, 0, 1]\n", "coincide"),
                                     ("fov_x_deg: 500\neye: [0, 0, 1]\nlook_at: [0, 0, 0]\n", "field of view"),
                                     ("T_world_cam: [[1, 0], [0, 1]]\n", "4x4"),
                                     ("lens: fisheye\n", "unknown camera keys"),
                                     ("- 1\n- 2\n", "mapping")])
def test_bad_camera_yaml_is_input_error(tmp_path, bad, msg):
    p = tmp_path / "bad.yaml"
    p.write_text(bad)
    with pytest.raises(InputError, match=msg):
        load_camera_yaml(p)


def test_camera_below_table_and_twin_without_splats_exit_2(tiny_twin, meshonly_twin, tmp_path, capsys):
    below = tmp_path / "below.yaml"
    below.write_text("eye: [0.1, 0.1, -0.3]\nlook_at: [0, 0, 0]\n")
    with pytest.raises(InputError, match="below the table"):
        check_camera(load_camera_yaml(below), DynamicScene.load(tiny_twin).table_height)
    from .rollouts import synthetic_rollout

    r = synthetic_rollout(0.1).save(tmp_path / "r.npz")
    code = main(["render", str(tiny_twin), "--camera", str(below), "--out", str(tmp_path / "v.mp4"),
                 "--rollout", str(r), "--no-robot"])
    assert code == 2 and "below the table" in capsys.readouterr().err
    assert not (tmp_path / "v.mp4").exists()
    code = main(["render", str(meshonly_twin), "--camera", "capture:0", "--out", str(tmp_path / "w.mp4"),
                 "--rollout", str(r)])
    assert code == 2 and "no splats" in capsys.readouterr().err
    code = main(["render", str(tiny_twin), "--camera", "capture:0", "--out", str(tmp_path / "x.mp4")])
    assert code == 2 and "no rollout" in capsys.readouterr().err


def test_camera_yaml_alias_bomb_is_refused_before_expanding(tmp_path):
    """Nested aliases (a few hundred bytes expanding to 10^9 floats) are refused by the bounded loader;
    this one expands to 10^5 nodes, harmless unbounded too, but above a camera's node limit."""
    lines = ["a0: &a0 [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 5)]
    p = tmp_path / "bomb.yaml"
    p.write_text("name: {" + ", ".join(lines) + "}\nK: *a4\n")
    with pytest.raises(InputError, match=r"bomb\.yaml.*aliases"):
        load_camera_yaml(p)


def test_capture_camera_too_large_to_render_names_the_cameras_file(tiny_twin, tmp_path):
    """The capture camera's size comes from the twin's cameras file: 12000x9000 there is refused (it took
    6 GB before the rasterizer failed); --width scales it down to something renderable."""
    import json
    import shutil

    twin = shutil.copytree(tiny_twin, tmp_path / "twin")
    p = twin / "poses" / "transforms.json"
    d = json.loads(p.read_text())
    scale = 12000 / d.get("w", d["frames"][0].get("w", 96))
    for block in [d] + d["frames"]:
        for k in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            if k in block:
                block[k] = int(block[k] * scale) if k in ("w", "h") else block[k] * scale
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"transforms\.json.*12000x9000.*--width"):
        resolve_camera("capture:0", twin)
    assert resolve_camera("capture:0", twin, width=640).width == 640


def test_render_with_nan_recorded_base_pose_exits_2_naming_results_json(tiny_twin, tmp_path, capsys):
    """render reads the base pose plan recorded in TWIN/robot/results.json: "nan" there made it fail with
    'negative dimensions' (exit 1)."""
    import json
    import shutil

    from .rollouts import synthetic_rollout

    twin = shutil.copytree(tiny_twin, tmp_path / "twin")
    (twin / "robot").mkdir(exist_ok=True)
    (twin / "robot" / "results.json").write_text(json.dumps({"base_pose": {"x": "nan", "y": 0, "z": 0, "yaw": 0}}))
    r = synthetic_rollout(0.1).save(tmp_path / "r.npz")
    code = main(["render", str(twin), "--camera", "capture:0", "--out", str(tmp_path / "v.mp4"), "--rollout", str(r)])
    assert code == 2 and "results.json" in capsys.readouterr().err
    assert not (tmp_path / "v.mp4").exists()


def test_render_refuses_the_rollout_of_an_earlier_twin(tiny_twin, tmp_path, capsys):
    """After a rebuild without --task, robot/rollout.npz of an earlier twin was played as this twin's (an
    arm moving nothing). It plays only when results.json was made on the twin as it is now."""
    import json
    import shutil

    from splattwin.robot.outputs import twin_digest

    from .rollouts import synthetic_rollout

    twin = tmp_path / "twin"
    shutil.copytree(tiny_twin, twin)
    (twin / "robot").mkdir(exist_ok=True)
    synthetic_rollout(0.1).save(twin / "robot" / "rollout.npz")
    below = tmp_path / "below.yaml"
    below.write_text("eye: [0.1, 0.1, -0.3]\nlook_at: [0, 0, 0]\n")
    args = ["render", str(twin), "--camera", str(below), "--out", str(tmp_path / "v.mp4"), "--no-robot"]
    for digest, expect in (("an earlier twin", "not this twin's to play"), (None, "no twin digest"),
                           (twin_digest(twin), "below the table")):   # this twin's: played (the camera fails)
        doc = {"success": True} if digest is None else {"success": True, "twin_digest": digest}
        (twin / "robot" / "results.json").write_text(json.dumps(doc))
        assert main(args) == 2
        assert expect in capsys.readouterr().err
