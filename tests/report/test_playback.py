"""The report's task-in-motion section: the photoreal MP4 embedded (the physics frames: the robot section), and the
filled hole regions outlined with their fraction of the picture."""

from __future__ import annotations

import base64
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1]))
from playback.conftest import write_twin  # noqa: E402
from playback.rollouts import synthetic_rollout  # noqa: E402

from splattwin.errors import InputError  # noqa: E402
from splattwin.playback.video import read_mp4  # noqa: E402
from splattwin.playback.episode import sample_indices  # noqa: E402
from splattwin.report.html import Report  # noqa: E402
from splattwin.report.options import ReportOptions  # noqa: E402
from splattwin.report.playback import fill_outline, playback_section, task_video  # noqa: E402


@pytest.fixture()
def twin_with_rollout(tmp_path):
    twin = write_twin(tmp_path / "twin")
    rollout = synthetic_rollout(0.6)
    rollout.save(twin / "robot" / "rollout.npz")
    return twin, rollout


def test_fill_outline_is_the_inner_boundary():
    m = np.zeros((9, 9), bool)
    m[2:7, 3:8] = True
    e = fill_outline(m)
    assert e.sum() == 2 * 5 + 2 * 3 and not e[3:6, 4:7].any() and np.all(e <= m)


def test_report_embeds_the_task_video_and_marks_the_fill(twin_with_rollout):
    twin, rollout = twin_with_rollout
    opts = ReportOptions(video_camera="view_0", video_fps=10.0, video_width=96)
    rep = Report("t")
    sec = rep.section("motion")
    playback_section(sec, twin, opts)
    page = rep.to_html()
    m = re.search(r'<video[^>]*src="data:video/mp4;base64,([A-Za-z0-9+/=]+)"', page)
    assert m, "no embedded MP4"
    mp4 = twin / "report" / "task_view_0.mp4"
    assert base64.b64decode(m.group(1)) == mp4.read_bytes()
    frames = read_mp4(mp4)
    assert len(frames) == len(sample_indices(rollout.t, 10.0)) and frames.shape[1:] == (72, 96, 3)
    assert "filled fraction of the picture" in page and "blue_box" in page

    v = task_video(twin, opts)     # cached: the same file, not rendered again
    assert v["mp4"] == mp4 and v["moved"] == ["blue_box"]
    assert 0.0 < v["fill_fraction"] < 0.5 and v["fill_area_m2"]["blue_box"] > 0.002   # the 5 x 4 cm foot
    # the outline is magenta and lies where the fill mask has its edge
    pic = v["picture"]
    magenta = np.all(np.abs(pic - [1.0, 0.0, 1.0]) < 1e-6, axis=-1)
    assert magenta.sum() > 10


def test_report_section_notes_without_rollout_or_splats(tmp_path, twin_with_rollout):
    rep = Report("t")
    twin = write_twin(tmp_path / "norollout")
    playback_section(rep.section("a"), twin)
    mesh = write_twin(tmp_path / "meshonly", with_splats=False)
    synthetic_rollout(0.2).save(mesh / "robot" / "rollout.npz")
    playback_section(rep.section("b"), mesh)
    page = rep.to_html()
    assert "no executed task to play" in page and "no photoreal playback" in page and "no splats" in page
    with pytest.raises(InputError):
        ReportOptions(video_fps=0).validate()


def test_report_base_pose_nan_in_results_json_is_an_input_error(tmp_path):
    """report's task video reads the recorded base pose: "nan" there is an InputError naming results.json
    (it was read unchecked, as by render)."""
    import json

    from splattwin.errors import InputError
    from splattwin.report.playback import _base

    (tmp_path / "robot").mkdir()
    (tmp_path / "robot" / "results.json").write_text(json.dumps({"base_pose": {"x": "nan", "y": 0, "z": 0, "yaw": 0}}))
    with pytest.raises(InputError, match=r"results\.json.*base_pose\.x"):
        _base(tmp_path)


def test_report_shows_the_mujoco_overview_once_in_the_robot_section(twin_with_rollout):
    """robot/frames/overview.png was embedded twice: in the robot section and again beside the task video.
    Now the robot section has it, and the video's caption points there."""
    import json

    from splattwin.io import write_image
    from splattwin.report.build import build_report
    from splattwin.report.html import picture_bytes
    from splattwin.robot.outputs import twin_digest

    twin, _ = twin_with_rollout
    step = {"index": 1, "pick": "blue_box", "goal": "region", "grasped": True, "placed": True, "at_rest": True,
            "robot_collisions": 0, "object_collisions": 0, "success": True, "failure": None}
    (twin / "robot" / "results.json").write_text(json.dumps({
        "task": "task.yaml", "planner": "rrt", "nominal": {"success": True, "steps": [step]},
        "twin_digest": twin_digest(twin)}))
    rng = np.random.default_rng(0)
    overview = write_image(twin / "robot" / "frames" / "overview.png", rng.integers(0, 255, (40, 60, 3), np.uint8))
    page = build_report(twin, options=ReportOptions(video_camera="view_0", video_fps=10.0, video_width=96)).read_text()
    data = base64.b64encode(picture_bytes(overview, photo=True)[1]).decode("ascii")
    assert page.count(data) == 1
    robot = page.split("Robot task in physics")[1].split("</section>")[0]
    motion = page.split("The task in motion")[1].split("</section>")[0]
    assert data in robot and "execution in MuJoCo" in robot
    assert "data:video/mp4" in motion and "the robot section above" in motion
    (twin / "robot" / "frames" / "overview.png").unlink()     # a run without GL (or --no-render)
    page = build_report(twin, options=ReportOptions(video_camera="view_0", video_fps=10.0, video_width=96)).read_text()
    assert "execution in MuJoCo" not in page and "no physics frames" in page
    assert "the robot section above" not in page


@pytest.mark.parametrize("info", [{"width": "<b>", "height": 72, "frames": 5, "fps": 10.0},
                                  {"width": 96, "height": 72, "frames": 5, "fps": "ten"}, ["not", "a", "dict"], None])
def test_a_cached_video_record_with_bad_numbers_is_rendered_again(twin_with_rollout, info):
    """report/task_X.json with the right key but its numbers text (a received twin's): the report stopped with
    a ValueError formatting them; now the video is rendered again and the record rewritten."""
    twin, _ = twin_with_rollout
    opts = ReportOptions(video_camera="view_0", video_fps=10.0, video_width=96)
    task_video(twin, opts)
    keyfile = twin / "report" / "task_view_0.json"
    rec = json.loads(keyfile.read_text())
    good = rec["info"]
    rec["info"] = info
    keyfile.write_text(json.dumps(rec))
    rep = Report("t")
    playback_section(rep.section("motion"), twin, opts)
    assert f"({good['width']}×{good['height']}, {good['frames']} frames" in rep.to_html()
    again = json.loads(keyfile.read_text())["info"]
    assert {k: again[k] for k in ("width", "height", "frames", "fps")} == {k: good[k] for k in ("width", "height",
                                                                                              "frames", "fps")}
