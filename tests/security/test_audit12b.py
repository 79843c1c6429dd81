"""Audit 12B: untrusted input in the code added since audit 8B (3e83055): model folders, twin records, video
frames, report pictures. Each test crafts the hostile file and fails without its fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from splattwin.errors import InputError


def _remote_code_model(folder: Path, marker: Path) -> Path:
    """A model folder whose config names an unknown model_type and its own Python (`auto_map`): loading it
    with trust_remote_code unset makes transformers ask whether to run evil.py, which writes `marker`."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"model_type": "evil_xyz",
                                                    "auto_map": {"AutoConfig": "evil.EvilConfig"}}))
    (folder / "evil.py").write_text(
        f"from pathlib import Path\nPath({str(marker)!r}).write_text('ran')\n"
        "from transformers import PretrainedConfig\n\n\nclass EvilConfig(PretrainedConfig):\n"
        "    model_type = 'evil_xyz'\n")
    return folder


def test_a_model_folders_own_code_never_runs_even_when_the_user_says_yes(tmp_path, monkeypatch):
    from transformers import AutoConfig

    from splattwin.semantics.segment import load_pretrained

    marker = tmp_path / "ran.txt"
    model = _remote_code_model(tmp_path / "model", marker)
    asked = []
    monkeypatch.setattr("builtins.input", lambda prompt="": asked.append(prompt) or "y")
    with pytest.raises(InputError, match="custom code"):
        load_pretrained(AutoConfig, str(model), "segmenter config")
    assert not asked, "transformers asked whether to run the folder's code"
    assert not marker.exists()


def _embedded_picture_sizes(html: str) -> list[tuple[int, int]]:
    """(width, height) of every picture embedded in a report page as a data URI."""
    import base64
    import io as _io
    import re

    from PIL import Image

    return [Image.open(_io.BytesIO(base64.b64decode(m))).size
            for m in re.findall(r'src="data:image/[a-z]+;base64,([A-Za-z0-9+/=]+)"', html)]


def _secret_png(path: Path) -> bytes:
    """A 13x7 picture (a size no other picture of the test twin has) standing for a private image."""
    import numpy as np

    from splattwin.io import write_image

    img = np.zeros((7, 13, 3), np.uint8)
    img[0, 0] = (1, 2, 3)
    write_image(path, img)
    return path.read_bytes()


@pytest.mark.parametrize("rel", ["poses/cameras.png", "splat/transients.png", "robot/overview.png",
                                 "semantics/label_maps/view_000.png"])
@pytest.mark.parametrize("absolute", [True, False])
def test_report_embeds_no_picture_a_link_brings_from_outside_the_twin(tmp_path, rel, absolute, caplog,
                                                                      test_module):
    import base64
    import os

    from splattwin.report.build import build_report

    from splattwin.robot.outputs import twin_digest

    helpers = test_module("report/test_build.py")
    twin = helpers._manifest_twin(tmp_path, scaled=True)
    helpers._robot_results(twin, twin_digest(twin))
    secret = _secret_png(tmp_path / "private.png")
    link = twin / rel
    link.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(tmp_path / "private.png" if absolute else os.path.relpath(tmp_path / "private.png", link.parent), link)
    if rel.startswith("semantics"):
        (twin / "semantics" / "fusion.json").write_text(json.dumps(
            {"options": {"kappa": 1.5, "iters": 1}, "objects": [], "label_map_views": ["view_000"]}))
    html = build_report(twin).read_text()
    assert base64.b64encode(secret).decode() not in html
    assert (13, 7) not in _embedded_picture_sizes(html)   # nor re-encoded (photos are embedded as JPEG)


def test_report_task_video_cached_as_a_link_out_of_the_twin_is_rendered_again(tmp_path):
    """report/task_X.mp4 linked to a file elsewhere, beside the key the twin's own files give: the report embedded
    that file as its video. Now a cached video must lie inside the twin, else it is rendered again."""
    import base64
    import os
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from playback.conftest import write_twin
    from playback.rollouts import synthetic_rollout

    from splattwin.report.html import Report
    from splattwin.report.options import ReportOptions
    from splattwin.report.playback import playback_section

    twin = write_twin(tmp_path / "twin")
    synthetic_rollout(0.6).save(twin / "robot" / "rollout.npz")
    opts = ReportOptions(video_camera="view_0", video_fps=10.0, video_width=96)
    playback_section(Report("t").section("motion"), twin, opts)     # renders; writes the video and its key
    mp4 = twin / "report" / "task_view_0.mp4"
    secret = tmp_path / "private.bin"
    secret.write_bytes(b"not for the report " * 50)
    mp4.unlink()
    os.symlink(os.path.relpath(secret, mp4.parent), mp4)
    rep = Report("t")
    playback_section(rep.section("motion"), twin, opts)
    assert base64.b64encode(secret.read_bytes()).decode() not in rep.to_html()
    assert not mp4.is_symlink() and secret.read_bytes() == b"not for the report " * 50


@pytest.mark.parametrize("where", ["absolute", "dotdot"])
def test_twin_json_refined_poses_path_is_confined_to_the_twin(tmp_path, where):
    """twin.json config.refined_poses named a file anywhere ("/x.json", "../../x.json"): render and the report
    video read its poses in place of the capture's. Now it is an InputError naming twin.json."""
    import os
    import sys

    import numpy as np

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from playback.conftest import write_twin

    from splattwin.capture import nerfstudio
    from splattwin.playback.cameras import capture_cameras, capture_cameras_path
    from splattwin.twin.manifest import Manifest

    twin = write_twin(tmp_path / "twin")
    names = [f.name for f in nerfstudio.read(capture_cameras_path(twin)).frames]
    far = np.eye(4)
    far[:3, 3] = 5.0
    outside = tmp_path / "elsewhere.json"
    outside.write_text(json.dumps({"convention": "T_world_cam, OpenCV", "poses": {n: far.tolist() for n in names}}))
    man = Manifest.load(twin)
    man.config["refined_poses"] = str(outside) if where == "absolute" else os.path.relpath(outside, twin)
    man.save(twin)
    with pytest.raises(InputError, match="refined_poses") as e:
        cams = capture_cameras(twin)
        assert not any(np.allclose(c.T_world_cam, far) for c in cams)   # (without the fix: they all are)
    assert e.value.path == twin / "twin.json"


def test_video_frames_larger_than_the_pixel_limit_are_refused_before_decoding(tmp_path, monkeypatch, cli):
    """A video's frames were decoded to RGB whatever their size (a photo's header is checked against
    SPLATTWIN_MAX_IMAGE_PIXELS, a video's was not: a 16000x16000 stream cost ~1 GB a frame). Now its declared
    size is checked when it is opened, and each frame's before it is converted. The limit is lowered here so
    the video stays tiny."""
    import numpy as np

    from splattwin import limits
    from splattwin.capture.video import extract_frames
    from splattwin.playback.video import write_mp4
    from security_helpers import assert_bad_input

    video = write_mp4(tmp_path / "clip.mp4", [np.full((48, 64, 3), 40 * i, np.uint8) for i in range(4)], fps=4)
    monkeypatch.setattr(limits, "MAX_IMAGE_PIXELS", 64 * 48 - 1)
    with pytest.raises(InputError, match="megapixels") as e:
        extract_frames(video, tmp_path / "frames", progress=False)
    assert e.value.path == video and not list((tmp_path / "frames").glob("*.png"))
    assert_bad_input(cli("capture", "frames", video, tmp_path / "out"), "clip.mp4", "megapixels")


def test_poses_report_bundled_record_removes_no_file_outside_the_bundle_folders(tmp_path):
    """poses_report.json's "bundled" list names the files an earlier save placed in images/, depth/, ...;
    "images/../frame.json" passed the folder test and the confinement (it stays in the folder), so saving
    poses there again deleted frame.json and transforms.json, and "images/./0.png" the photo this run had just
    bundled as images/0.png. Now only a recorded path in normal form is removed."""
    from splattwin.capture.bundle import remove_unbundled
    from splattwin.poses.estimate import _bundled_record

    out = tmp_path / "poses"
    (out / "images").mkdir(parents=True)
    for n in ("frame.json", "transforms.json", "images/old.png", "images/0.png"):
        (out / n).write_text("x")
    (out / "poses_report.json").write_text(json.dumps(
        {"bundled": ["images/../frame.json", "images/x/../../transforms.json", "images/old.png", "images/./0.png"]}))
    removed = remove_unbundled(out, _bundled_record(out), placed=["images/0.png"])   # 0.png: placed by this run
    assert removed == [out / "images" / "old.png"]
    assert (out / "frame.json").is_file() and (out / "transforms.json").is_file() and (out / "images/0.png").is_file()


def test_model_config_and_twin_json_nested_deeply_are_unknown_not_a_traceback(tmp_path):
    """The segmenter's config.json (its model_type names the segmenter family) and twin.json (the summary's
    ground-truth placement) were read whole, unbounded, and parsed with json.loads: 200000 '[' raised
    RecursionError through `segmenter_kind` (pre-flight, build) and after a finished build."""
    from splattwin.pipeline.cli import _gt_placement
    from splattwin.semantics.models import segmenter_kind
    from splattwin.semantics.options import SegmentOptions

    model = tmp_path / "model"
    model.mkdir()
    (model / "config.json").write_text("[" * 200_000)
    assert segmenter_kind(SegmentOptions(segmenter=str(model))) is None
    (tmp_path / "twin.json").write_text('{"config": ' * 200_000)
    assert _gt_placement(tmp_path / "twin.json") == ""


@pytest.mark.parametrize("part", ["appearance", "poses"])
def test_checkpoint_corrections_of_nan_are_refused_on_resume(tiny_dataset, tmp_path, part):
    """check_state held the Gaussians to finite values but not the learnt corrections added since (per-view
    appearance gains, pose corrections): a received checkpoint of NaN gains resumed into NaN renders."""
    import torch

    from splattwin.capture import load_dataset
    from splattwin.splat import checkpoint as ckpt_io
    from splattwin.splat.trainer import TrainConfig, Trainer

    cfg = TrainConfig(iters=12, sh_degree=0, checkpoint_every=6, progress=False, backend="cpu", max_gaussians=500,
                      init="random", init_points=200, appearance="gain" if part == "appearance" else "off",
                      refine_poses=part == "poses")
    ds = load_dataset(tiny_dataset)
    out = tmp_path / "out"
    Trainer(ds, out, cfg).run()
    ckpts = sorted((out / "checkpoints").iterdir())
    for c in ckpts[1:]:
        c.unlink()
    sd = ckpt_io.load(ckpts[0])
    st = sd[part]
    key = "params" if part == "appearance" else "xi"
    if isinstance(st[key], torch.Tensor):
        st[key] = torch.full_like(st[key], float("nan"))
    else:
        st[key] = [torch.full_like(t, float("nan")) for t in st[key]]
    ckpt_io.save(ckpts[0], sd)
    with pytest.raises(InputError, match="NaN") as e:
        Trainer(ds, out, cfg).run(resume=True)
    assert e.value.path == ckpts[0]


@pytest.mark.parametrize("bad, needle", [
    ("text", "must be a number"), ("bool", "must be a number"), ("scaled", "not a rigid transform"),
    ("far", "position")])
def test_refined_poses_hold_numbers_a_rotation_and_a_plausible_position(tmp_path, bad, needle):
    """refined_poses.json (a twin's splat/, read by the semantics and twin stages and render): np.asarray read
    "1.0" and true as numbers and any finite 4x4 as a pose (a scaled or sheared matrix, a position 1e300 m
    away). Now each pose is 16 numbers, a rotation and a position within MAX_POSITION, as a capture's."""
    import numpy as np

    from splattwin.splat import refined_poses

    T = np.eye(4).tolist()
    T = {"text": [[str(x) for x in r] for r in T], "bool": [[True, False, False, 0], *T[1:]],
         "scaled": (np.diag([2.0, 2.0, 2.0, 1.0])).tolist(), "far": [[1, 0, 0, 1e300], *T[1:]]}[bad]
    path = tmp_path / refined_poses.FILE
    path.write_text(json.dumps({"convention": refined_poses.CONVENTION, "poses": {"view_000": T}}))
    with pytest.raises(InputError, match=needle) as e:
        refined_poses.read(path)
    assert e.value.path == path
    path.write_text(json.dumps({"convention": refined_poses.CONVENTION, "poses": {"view_000": np.eye(4).tolist()}}))
    assert np.array_equal(refined_poses.read(path)["train"]["view_000"], np.eye(4))


def test_colmap_text_image_id_of_thousands_of_digits_is_bad_input(tmp_path, cli):
    """images.txt's image id was read with int() when all digits: 5000 digits raised Python's ValueError
    (4300-digit limit), reported as "internal error, a bug in splattwin" (exit 1). Now ids are ascii_uint
    (at most 18 digits) and pycolmap's refusal of the line is the error, naming the model (exit 2)."""
    from security_helpers import assert_bad_input

    sparse = tmp_path / "cap" / "sparse" / "0"
    sparse.mkdir(parents=True)
    (tmp_path / "cap" / "images").mkdir()
    (sparse / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    (sparse / "images.txt").write_text("9" * 5000 + " 1 0 0 0 0 0 0 1 a.png\n\n")
    (sparse / "points3D.txt").write_text("")
    assert_bad_input(cli("capture", "info", tmp_path / "cap"), "sparse/0")


def _two_photos(folder: Path) -> list[Path]:
    import numpy as np

    from splattwin.io import write_image

    rng = np.random.default_rng(0)
    return [write_image(folder / f"{i}.png", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)) for i in range(2)]


def test_sfm_resume_checks_the_finished_model_of_the_work_folder(tmp_path):
    """OUT/sfm (a received poses or twin folder built into again) with sfm_config.json matching this run and
    sparse/done: its model went to pycolmap unchecked (cameras.bin claiming 2^40 cameras: ValueError, exit 1).
    Now it is checked as any COLMAP model: InputError naming the file."""
    import struct

    from splattwin.poses.sfm import SfmOptions, _config_key, image_layout, run_sfm

    photos = _two_photos(tmp_path / "images")
    work = tmp_path / "out" / "sfm"
    (work / "sparse").mkdir(parents=True)
    opts = SfmOptions()
    (work / "sfm_config.json").write_text(json.dumps(_config_key(opts, sorted(image_layout(photos)[1]))))
    (work / "sparse" / "done").write_text("{}")
    (work / "sparse" / "cameras.bin").write_bytes(struct.pack("<Q", 1 << 40))
    for n in ("images.bin", "points3D.bin"):
        (work / "sparse" / n).write_bytes(struct.pack("<Q", 0))
    with pytest.raises(InputError) as e:
        run_sfm(photos, work, opts, progress=False)
    assert "cameras.bin" in str(e.value.path)


def test_sfm_work_records_naming_models_outside_the_folder_are_not_reused(tmp_path, monkeypatch):
    """models/<attempt>.json lists the models mapping made, reused on resume: a record naming /elsewhere/model
    had pycolmap read a model from outside the folder. Now such a record counts as absent: mapping runs again."""
    from splattwin.poses import colmap_process, sfm
    from splattwin.poses.progress import StageProgress

    photos = _two_photos(tmp_path / "images")
    work = tmp_path / "out" / "sfm"
    elsewhere = tmp_path / "elsewhere" / "model"
    elsewhere.mkdir(parents=True)
    (work / "models" / "a0").mkdir(parents=True)
    (work / "models" / "a0.json").write_text(json.dumps({"paths": [str(elsewhere)]}))
    ran = []

    def run_step(job, *a, **k):
        ran.append(job["step"])
        return {"models": [{"path": str(work / "models" / "a0" / "0")}]}, colmap_process.StepStats(0.0, 0)

    monkeypatch.setattr(colmap_process, "run_step", run_step)
    root, names = sfm.image_layout(photos)
    run = sfm.SfmRun(work, root, sorted(names), sfm.SfmOptions(), StageProgress(False))
    got = run.map(work / "database.db", sfm.Attempt("a0", "test"), "test")
    assert ran == ["map"] and got == [work / "models" / "a0" / "0"]


def test_recording_state_nested_deeply_is_no_state(tmp_path):
    """`plan --record DIR` reads the dataset folder's recording state: json.loads of 200000 '[' raised
    RecursionError (only OSError and ValueError were caught). Now it is read bounded: no state."""
    from splattwin.playback.record import _read_state

    p = tmp_path / "state.json"
    p.write_text("[" * 200_000)
    assert _read_state(p) == {}


def test_triangulation_resume_checks_its_finished_model(tmp_path):
    """Known poses: points are triangulated in OUT/sfm and resumed from triangulated/done. That model went to
    pycolmap unchecked (cameras.bin claiming 2^40 cameras: ValueError, exit 1); now it is checked as SfM's
    (InputError naming the file)."""
    import struct

    import numpy as np

    from splattwin.capture.camera import Camera
    from splattwin.poses.sfm import SfmOptions
    from splattwin.poses.triangulate import triangulate_known_poses

    photos = _two_photos(tmp_path / "images")
    K = np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    cams = [Camera(K=K, width=64, height=48, T_world_cam=np.eye(4)) for _ in photos]
    cams[1].T_world_cam[0, 3] = 0.1
    work, opts = tmp_path / "work", SfmOptions()
    (work / "triangulated").mkdir(parents=True)
    # the record of a finished run with these images and cameras (triangulate_known_poses' key)
    (work / "triangulation_config.json").write_text(json.dumps(
        {"images": ["0.png", "1.png"], "cameras": [c.to_dict() for c in cams], "max_image_size": opts.max_image_size,
         "max_num_features": opts.max_num_features, "peak_threshold": opts.peak_threshold, "neighbours": 20}))
    (work / "triangulated" / "done").write_text("{}")
    (work / "triangulated" / "cameras.bin").write_bytes(struct.pack("<Q", 1 << 40))
    for n in ("images.bin", "points3D.bin"):
        (work / "triangulated" / n).write_bytes(struct.pack("<Q", 0))
    with pytest.raises(InputError) as e:
        triangulate_known_poses(photos, cams, work, opts, progress=False)
    assert "cameras.bin" in str(e.value.path)


def test_report_picture_with_megabytes_appended_is_not_embedded_whole(tmp_path):
    """A twin's picture is embedded as its PNG bytes: a 10x10 PNG with 3 MiB appended after IEND (or in an
    ancillary chunk) put all of it, base64, into the report. Now a PNG file larger than its pixels could need
    is decoded and written again."""
    import numpy as np

    from splattwin.io import write_image
    from splattwin.report.html import Report

    p = write_image(tmp_path / "cameras.png", np.full((10, 10, 3), 7, np.uint8))
    with open(p, "ab") as f:
        f.write(b"\0" * (3 << 20))
    rep = Report("t")
    rep.section("s").image(p)
    assert len(rep.to_html()) < 100_000


def test_report_reads_a_twins_records_within_the_record_limit(tmp_path, monkeypatch, test_module):
    """The report read the stages' JSON records (metrics.json, train.json, results.json, ...) within the 1 GiB
    meant for COCO files, ~10 GB to parse; now within SPLATTWIN_MAX_RECORD_BYTES (lowered here)."""
    from splattwin import limits
    from splattwin.report.build import build_report

    helpers = test_module("report/test_build.py")
    twin = helpers._twin(tmp_path, views=[{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}], padding="x" * 5000)
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 4000)
    assert "24.5" not in build_report(twin).read_text()
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 64 << 20)
    assert "24.5" in build_report(twin).read_text()


def test_a_record_nested_too_deeply_to_write_back_is_refused_when_read(tmp_path):
    """json.loads reads ~990 levels, but writing such a document back recursed past Python's limit: `plan`
    recording its run in a received twin's pipeline.json (900 levels) ended in RecursionError after the task
    ran. Records (read within MAX_RECORD_BYTES) now nest at most MAX_RECORD_DEPTH levels: InputError."""
    from splattwin.limits import MAX_RECORD_BYTES, read_json
    from splattwin.report.build import record_plan_run

    twin = tmp_path / "twin"
    twin.mkdir()
    (twin / "pipeline.json").write_text('{"robot": {}, "x": ' + "[" * 900 + "]" * 900 + "}")
    assert record_plan_run(twin, 1.0, 0.5) is False
    with pytest.raises(InputError, match="nested"):
        read_json(twin / "pipeline.json", max_bytes=MAX_RECORD_BYTES)
    (twin / "pipeline.json").write_text('{"robot": {}, "x": ' + "[" * 50 + "]" * 50 + "}")
    assert record_plan_run(twin, 1.0, 0.5) is True


def test_render_and_view_read_robot_results_within_the_record_limit(tmp_path, monkeypatch):
    """robot/results.json of a received twin is read by `render` (the failed-run note, the stale check) and the
    viewer (the stale-motion check) within the 64 MiB record limit, not the 1 GiB limit meant for COCO files
    (~10 GB to parse at that size). Over the limit it counts as unreadable: no note, and no motion vouched for."""
    import json

    from splattwin import limits
    from splattwin.playback.cli import _failed_run
    from splattwin.playback.view_model import _made_on_another_twin
    from splattwin.robot.outputs import stale_results

    rj = tmp_path / "robot" / "results.json"
    rj.parent.mkdir()
    rj.write_text(json.dumps({"nominal": {"success": False, "steps": [{"index": 1, "pick": "cube", "goal": "box",
                                                                       "success": False, "failure": "slipped"}]},
                              "twin_digest": "0" * 64, "pad": "x" * 5000}))
    assert "slipped" in _failed_run(rj)                                   # read within the limit
    assert "earlier state" in _made_on_another_twin(tmp_path)
    assert "earlier state" in stale_results(tmp_path)
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 4000)
    assert _failed_run(rj) is None
    assert _made_on_another_twin(tmp_path) is None
    assert stale_results(tmp_path) == "robot/results.json is unreadable"
