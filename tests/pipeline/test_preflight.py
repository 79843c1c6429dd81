"""Pre-flight (`splattwin.pipeline.preflight`, `splattwin.semantics.models`): a build that cannot succeed
stops with exit 2 before pose estimation, naming the models, the missing scale or the resource."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.cli import main as cli
from splattwin.errors import InputError
from splattwin.io import write_image
from splattwin.pipeline import preflight as pf
from splattwin.pipeline.options import BuildOptions
from splattwin.poses.options import PoseOptions
from splattwin.robot.options import RobotOptions
from splattwin.semantics import models
from splattwin.semantics.options import SegmentOptions, SemanticsOptions


def _images(root: Path, n: int = 6, w: int = 64, h: int = 48) -> Path:
    rng = np.random.default_rng(0)
    for i in range(n):
        write_image(root / f"img_{i:02d}.png", rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    return root


def _model_dir(root: Path, model_type: str) -> Path:
    root.mkdir(parents=True)
    (root / "config.json").write_text(json.dumps({"model_type": model_type}))
    (root / "model.safetensors").write_bytes(b"\0" * 8)
    for name in ("preprocessor_config.json", "tokenizer.json"):   # what the processors load
        (root / name).write_text("{}")
    return root


def test_prompt_without_weights_names_every_model_and_stops_before_poses(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(models, "_local_file", lambda model, name: None)  # an empty Hugging Face cache
    out = tmp_path / "twin"
    code = cli(["build", str(_images(tmp_path / "imgs")), "--out", str(out), "--prompt", "red box. cup",
                "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "IDEA-Research/grounding-dino-tiny" in err and "facebook/sam-vit-base" in err
    assert "Grounding DINO" in err and "SAM" in err and "hf download" in err
    assert not (out / "poses").exists() and not (out / "splat").exists()


def test_models_from_local_folders(tmp_path):
    det = _model_dir(tmp_path / "dino", "grounding-dino")
    sam = _model_dir(tmp_path / "sam", "sam")
    assert models.missing_models_error(SegmentOptions(detector=str(det), segmenter=str(sam))) is None
    # SAM 3 segments the phrases itself: no detector needed
    sam3 = _model_dir(tmp_path / "sam3", "sam3")
    opts = SegmentOptions(detector=str(tmp_path / "absent"), segmenter=str(sam3))
    assert [r for r, _ in models.required_models(opts)] == ["SAM 3 segmenter"]
    assert models.missing_models_error(opts) is None
    # one present, one missing: both listed, only the missing one as MISSING
    e = models.missing_models_error(SegmentOptions(detector=str(det), segmenter=str(tmp_path / "nosam")))
    assert e is not None and "(present)" in e.problem and f"{tmp_path / 'nosam'}' (MISSING)" in e.problem
    # config without weights is not available
    (sam / "model.safetensors").unlink()
    assert not models.is_available(str(sam))


def test_task_on_an_unscaled_capture_stops_before_sfm(tmp_path, capsys):
    out = tmp_path / "twin"
    code = cli(["build", str(_images(tmp_path / "imgs")), "--out", str(out), "--task", "default", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "--task needs a metric twin" in err and "--known-length" in err and "--marker-size" in err
    assert "--robot-poses" in err and str(tmp_path / "imgs") in err
    assert not (out / "poses").exists()


def test_no_masks_stops_before_sfm_and_until_splats_builds_without(tmp_path, capsys, monkeypatch):
    """An image folder with neither --masks nor --prompt: the semantics stage could only fail, after SfM and
    training (minutes to hours); pre-flight says so at once and how to build the splats alone."""
    imgs = _images(tmp_path / "imgs")
    out = tmp_path / "twin"
    code = cli(["build", str(imgs), "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "no 2D masks" in err and "--masks" in err and "--prompt" in err and "--until splats" in err
    assert str(imgs) in err and not (out / "poses").exists()
    o = BuildOptions(input=str(imgs))
    for until in ("scene", "poses", "splats"):      # the stages before semantics need no masks
        pf.run_preflight(o, out, imgs, None, tmp_path / "frames", until=until)
    for until in ("semantics", "twin", "report", None):
        with pytest.raises(InputError, match="no 2D masks"):
            pf.run_preflight(o, out, imgs, None, tmp_path / "frames", until=until)
    # the embedded scene (generated, or a written scene folder as input) brings its own simulated masks
    pf.run_preflight(BuildOptions(), out, None, None, tmp_path / "frames")
    # a folder with a scene.json but no masks of its own: named here too, not after training (audit 8c H2)
    (imgs / "scene.json").write_text(json.dumps({"objects": [{"name": "box", "label": 1}]}))
    with pytest.raises(InputError, match="no 2D masks"):
        pf.run_preflight(o, out, imgs, imgs, tmp_path / "frames")
    pf.run_preflight(o, out, imgs, imgs, tmp_path / "frames", until="splats")


def test_every_independent_problem_is_named_in_one_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(models, "_local_file", lambda model, name: None)
    imgs = _images(tmp_path / "imgs")
    code = cli(["build", str(imgs), "--out", str(tmp_path / "twin"), "--prompt", "red box", "--task", "default",
                "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "pre-flight found 2 problems" in err
    assert "1. " in err and "grounding-dino" in err and "2. " in err and "--task needs a metric twin" in err
    assert not (tmp_path / "twin" / "poses").exists()


def test_scale_sources_satisfy_the_task_check(tmp_path):
    imgs = _images(tmp_path / "imgs")
    for poses in (PoseOptions(known_length="camera_height=0.5"), PoseOptions(marker_size=0.05),
                  PoseOptions(robot_poses=tmp_path / "robot.json")):
        o = BuildOptions(input=str(imgs), poses=poses, robot=RobotOptions(task="default"))
        pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="splats")  # no error
    P = PoseOptions
    assert pf.unscaled_reason(P(), has_poses=False, fmt="images", frame_json_beside=False) is not None
    assert pf.unscaled_reason(P(), has_poses=True, fmt="nerfstudio", frame_json_beside=False) is None
    assert "COLMAP" in pf.unscaled_reason(P(), has_poses=True, fmt="colmap", frame_json_beside=False)
    assert pf.unscaled_reason(P(), has_poses=True, fmt="colmap", frame_json_beside=True) is None
    assert pf.unscaled_reason(P(method="sfm"), has_poses=True, fmt="nerfstudio", frame_json_beside=True)
    # SfM output in other layouts, and --scale
    assert "3DGS" in pf.unscaled_reason(P(), has_poses=True, fmt="cameras.json", frame_json_beside=False)
    assert "nerfstudio" in pf.unscaled_reason(P(), True, "nerfstudio", False, sfm_derived=True)
    assert pf.unscaled_reason(P(scale="metric"), True, "colmap", False) is None
    assert pf.unscaled_reason(P(scale="unscaled"), True, "nerfstudio", False) == "--scale unscaled"
    # SfM on an RGB-D capture: the depth images give the scale
    assert pf.unscaled_reason(P(), has_poses=False, fmt="bop", frame_json_beside=False, has_depth=True) is None
    assert pf.unscaled_reason(P(scale_from_depth=False), False, "bop", False, has_depth=True) is not None


def test_memory_and_disk_refused_only_when_clearly_insufficient(tmp_path, monkeypatch):
    imgs = _images(tmp_path / "imgs")
    o = BuildOptions(input=str(imgs))
    monkeypatch.setattr(pf, "available_memory", lambda: 64 * pf.GIB)
    monkeypatch.setattr(pf, "free_disk", lambda p: 500 * pf.GIB)
    info = pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="splats")
    assert info["views"] == 6 and 1.0 < info["memory_gib"] < 8
    need = info["memory_gib"] * pf.GIB
    monkeypatch.setattr(pf, "available_memory", lambda: need / 1.2)   # tight: a warning only
    pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="splats")
    monkeypatch.setattr(pf, "available_memory", lambda: need / 2)     # clearly short
    with pytest.raises(InputError, match="not enough memory.*--cpu-max-side"):
        pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="splats")
    monkeypatch.setattr(pf, "available_memory", lambda: 64 * pf.GIB)
    monkeypatch.setattr(pf, "free_disk", lambda p: 0.01 * pf.GIB)
    with pytest.raises(InputError, match="not enough disk space"):
        pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="splats")


def test_estimate_grows_with_resolution_and_budget():
    small = pf.estimate([(4032, 3024)] * 20, [(640, 480)] * 20, 28_000, True, 0)
    full = pf.estimate([(4032, 3024)] * 20, [(4032, 3024)] * 20, 28_000, True, 0)
    more = pf.estimate([(4032, 3024)] * 20, [(640, 480)] * 20, 1_000_000, True, 0)
    assert full.memory > small.memory + 20 * 4032 * 3024 * 12 * 0.9
    assert more.memory > small.memory and more.disk > small.disk
    assert "SfM" in small.parts and "SfM" not in pf.estimate([(64, 48)], [(64, 48)], 100, False, 0).parts


def test_bad_mask_folder_found_at_preflight(tmp_path, capsys):
    imgs = _images(tmp_path / "imgs")
    masks = tmp_path / "masks"
    write_image(masks / "img_00" / "box.png", np.full((10, 10), 255, np.uint8))  # not the image size
    out = tmp_path / "twin"
    code = cli(["build", str(imgs), "--out", str(out), "--masks", str(masks), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "box.png" in err and not (out / "poses").exists()


def test_estimate_uses_the_trainers_default_budget_and_the_larger_phase():
    from splattwin.splat.resolution import capacity

    sizes, train = [(1080, 1920)] * 9, [(360, 640)] * 9
    auto = pf.estimate(sizes, train, 0, True, 0)
    cap = capacity(360 * 640)[1]
    assert auto.parts["Gaussians"] == cap * pf.BYTES_PER_GAUSSIAN
    assert auto.memory == pf.estimate(sizes, train, cap, True, 0).memory
    # SfM runs in its own process before training: the peak is one phase, not their sum
    assert auto.memory < sum(auto.parts.values())
    no_sfm = pf.estimate(sizes, train, cap, False, 0)
    assert auto.memory >= no_sfm.memory and no_sfm.memory == sum(no_sfm.parts.values())


def test_bad_training_option_stops_before_poses_with_the_other_problems(tmp_path, capsys):
    """A training option out of range (here the rasterizer's low-pass) is named at pre-flight, with the
    other problems, not after pose estimation; a build that stops before the splat stage is not held up
    by it."""
    from splattwin.splat.config import TrainConfig

    imgs = _images(tmp_path / "imgs")
    out = tmp_path / "twin"
    code = cli(["build", str(imgs), "--out", str(out), "--splat.eps2d", "-1", "--task", "default", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "pre-flight found 3 problems" in err
    assert "--eps2d must be in [0, 10]" in err and "--task needs a metric twin" in err and "no 2D masks" in err
    assert not (out / "poses").exists()
    bad = BuildOptions(input=str(imgs), splat=TrainConfig(drop_rate=1.5))
    pf.run_preflight(bad, out, imgs, None, tmp_path / "frames", until="poses")
    with pytest.raises(InputError, match="--drop-rate must be in"):
        pf.run_preflight(bad, out, imgs, None, tmp_path / "frames", until="splats")


def _jpegs(root: Path, n: int = 6, w: int = 64, h: int = 48) -> Path:
    from PIL import Image

    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(root / f"img_{i:02d}.jpg", quality=90)
    return root


def test_truncated_photo_stops_the_build_before_sfm_naming_the_users_file(tmp_path, capsys):
    """A photo cut short (an interrupted copy) used to pass pre-flight and SfM and fail only at training,
    naming the twin's copy of it; pre-flight now names the user's file and nothing is built."""
    imgs = _jpegs(tmp_path / "imgs")
    bad = imgs / "img_03.jpg"
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size * 2 // 3])
    out = tmp_path / "twin"
    code = cli(["build", str(imgs), "--out", str(out), "--until", "splats", "--iters", "20", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and f"{bad}: image is truncated or corrupt" in err
    assert not (out / "poses").exists() and not (out / "pipeline.json").exists()
    # `splattwin poses` on the same folder stops too, before SfM writes anything
    assert cli(["poses", str(imgs), str(tmp_path / "p")]) == 2
    assert f"{bad}: image is truncated" in capsys.readouterr().err
    assert not (tmp_path / "p" / "transforms.json").exists() and not (tmp_path / "p" / "sfm").exists()


def test_a_preflight_failure_on_rotated_photos_leaves_no_folder(tmp_path, capsys):
    """The pre-flight writes upright copies of EXIF-rotated photos into OUT/capture/frames/upright; when it
    then failed (no masks), that folder stayed behind in an output folder the run had created."""
    from PIL import Image

    src = tmp_path / "imgs"
    src.mkdir()
    rng = np.random.default_rng(0)
    for i in range(6):
        ex = Image.Exif()
        ex[0x0112] = 6   # stored rotated: shown turned 90 degrees
        Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(src / f"img_{i:02d}.png", exif=ex)
    out = tmp_path / "twin"
    code = cli(["build", str(src), "--out", str(out), "--task", "default", "--no-progress"])
    assert code == 2 and "--task needs a metric twin" in capsys.readouterr().err
    assert not out.exists()
    # a folder that was there before keeps what it held
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert cli(["build", str(src), "--out", str(out), "--task", "default", "--no-progress"]) == 2
    assert (out / "notes.txt").is_file() and (out / "capture" / "frames" / "upright").is_dir()


def test_prompt_names_are_checked_before_any_work(tmp_path):
    """A prompt phrase that names a reserved object ('table') was refused only at the semantics stage, after
    SfM and training (with the models present); the pre-flight now says so with the other problems."""
    imgs = _images(tmp_path / "imgs")
    o = BuildOptions(input=str(imgs), semantics=SemanticsOptions(prompt="table. mug"))
    with pytest.raises(InputError) as e:
        pf.run_preflight(o, tmp_path / "twin", imgs, None, tmp_path / "frames", until="semantics")
    assert "table" in str(e.value) and "--prompt" in str(e.value)


def test_task_stops_before_training_when_the_poses_came_out_unscaled(tmp_path):
    """The pre-flight lets an RGB-D capture without poses through (its depth should give the scale); when the
    depth gave none, the build used to train and fuse before the robot stage refused the task."""
    from splattwin import io
    from splattwin.pipeline.build import _check_task_scale
    from splattwin.pipeline.runner import Context
    from splattwin.poses.twin_frame import TwinFrame
    import dataclasses

    out = tmp_path / "twin"
    io.write_json(out / "poses" / "frame.json", dataclasses.asdict(TwinFrame(source="unscaled", scaled=False)))
    io.write_json(out / "poses" / "poses_report.json", {"depth_scale": {"error": "the depth images put the scene "
                                                                               "9.7 m from the cameras"}})
    ctx = Context(out=out, options={}, config=BuildOptions(robot=RobotOptions(task="default")))
    with pytest.raises(InputError) as e:
        _check_task_scale(ctx)
    assert "9.7 m" in str(e.value) and "nothing was trained" in str(e.value)
    _check_task_scale(Context(out=out, options={}, config=BuildOptions()))          # no task: fine
    io.write_json(out / "poses" / "frame.json", dataclasses.asdict(TwinFrame(source="table_plane+depth", scaled=True)))
    _check_task_scale(ctx)                                                            # metric: fine


def _tiny_robot_capture(root: Path, fmt: str = "bop") -> Path:
    from splattwin.scene import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    return write_robot_capture(root, SceneOptions(seed=0, width=64, height=48, supersample=1),
                               RobotCaptureOptions(views=4, width=64, height=48, format=fmt), progress=False)


def test_robot_capture_without_masks_uses_its_own_and_preflight_checks_them(tmp_path, caplog):
    """Audit 8c H2: `scene generate --robot-capture bop` built without --masks failed (exit 2) only at the
    semantics stage, after poses and splats ("masks/noisy: no noisy masks"). The capture's own masks
    (BOP mask_visib/, TUM masks/) are now the default, said in the log, and checked before any stage; a
    capture without any stops at pre-flight, in seconds, nothing trained."""
    import logging
    import shutil
    import time

    from splattwin.semantics.stage import load_stage_masks, scene_default_masks

    cap = _tiny_robot_capture(tmp_path / "cap")
    assert scene_default_masks(cap) == cap / "mask_visib"
    o = BuildOptions(input=str(cap))
    with caplog.at_level(logging.INFO, logger="splattwin.semantics.stage"):
        pf.run_preflight(o, tmp_path / "twin", cap, cap, tmp_path / "frames")
    assert "mask_visib" in caplog.text and "no --masks" in caplog.text
    from splattwin.capture import load_dataset

    ds = load_dataset(cap)
    own, where = load_stage_masks(o.semantics, ds.frames, cap)
    given, _ = load_stage_masks(SemanticsOptions(masks=str(cap / "mask_visib")), ds.frames, cap)
    assert where == cap / "mask_visib" and own.views == given.views and own.objects == given.objects
    assert set(own.objects.values()) >= {"toy_hammer", "yellow_cube"}
    tum = _tiny_robot_capture(tmp_path / "tum", "tum")
    assert scene_default_masks(tum) == tum / "masks"
    pf.run_preflight(BuildOptions(input=str(tum)), tmp_path / "twin_t", tum, tum, tmp_path / "frames_t")

    # the capture without its masks: exit 2 at once, naming the capture, no stage run
    shutil.rmtree(cap / "mask_visib")
    out = tmp_path / "twin2"
    t0 = time.perf_counter()
    code = cli(["build", str(cap), "--out", str(out), "--no-progress", "--iters", "30"])
    assert code == 2 and time.perf_counter() - t0 < 30
    assert not (out / "poses").exists() and not (out / "splats").exists()
    # a bad mask file of the capture's own is found at pre-flight too
    cap2 = _tiny_robot_capture(tmp_path / "cap2")
    bad = sorted((cap2 / "mask_visib").glob("*.png"))[0]
    write_image(bad, np.full((10, 10), 255, np.uint8))
    with pytest.raises(InputError, match=bad.name):
        pf.run_preflight(BuildOptions(input=str(cap2)), tmp_path / "twin3", cap2, cap2, tmp_path / "frames3")


def test_known_length_naming_an_image_not_in_the_capture_stops_before_sfm(tmp_path, capsys):
    """`build photos/ --known-length baseline@nope.jpg,frame000020.jpg=0.1` ran the whole SfM (a minute on the
    real cake) before "known length refers to image 'nope.jpg', which is not among the registered images";
    a malformed value stopped only once the poses stage began. Both stop at pre-flight now, naming the flag."""
    imgs = _images(tmp_path / "imgs")
    out = tmp_path / "twin"
    code = cli(["build", str(imgs), "--out", str(out), "--until", "poses", "--no-progress",
                "--known-length", "baseline@nope.jpg,img_01=0.1"])
    err = capsys.readouterr().err
    assert code == 2 and "--known-length" in err and "'nope.jpg'" in err and "img_00.png" in err, err
    assert "img_01" not in err.split("no image named")[1].split("in this capture")[0]   # found by its stem
    assert not (out / "poses").exists()
    code = cli(["build", str(imgs), "--out", str(out), "--until", "poses", "--no-progress",
                "--known-length", "camera_height=-1"])
    err = capsys.readouterr().err
    assert code == 2 and "positive number of metres" in err and not (out / "poses").exists(), err
    for bad, why in (("camera_height=-1", "positive number of metres"), ("height=0.4", "use camera_height or "
                     "baseline"), ("baseline@img_00=0.1", "exactly two images")):
        with pytest.raises(InputError, match=why) as e:
            pf.check_known_length(bad, None)
        assert str(e.value).startswith(f"--known-length {bad!r}: ")   # the flag and the value given
    from splattwin.capture import load_dataset

    ds = load_dataset(imgs)
    for good in ("baseline@img_00.png,img_03=0.2", "camera_height@img_02=0.4", "camera_height=0.45"):
        pf.check_known_length(good, ds)   # file names with or without the suffix
