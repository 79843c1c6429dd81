"""SfM choices without running COLMAP: options, matcher, threads, camera groups, retry plan and loop,
failure reasons, progress lines."""

from __future__ import annotations

import io as _io
from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses.sfm import (Attempt, AttemptOutcome, CameraGroup, SfmOptions, camera_groups, choose_matcher,
                                 explain_failures, extraction_threads, first_octave, mapping_options, retry_plan,
                                 run_plan)


# -- options ---------------------------------------------------------------------------------------------
def test_defaults_bound_size_and_features():
    o = SfmOptions()
    assert o.max_image_size == 1600 and 0 < o.max_num_features <= 8192 and o.num_threads == 0 and o.retry
    o.validate()


@pytest.mark.parametrize("kw, word", [({"max_image_size": 10}, "max-image-size"), ({"max_num_features": 5}, "max-features"),
                                      ({"num_threads": -2}, "threads"), ({"matcher": "magic"}, "matcher"),
                                      ({"max_memory_gib": 0}, "memory"), ({"sequential_overlap": 0}, "overlap")])
def test_bad_options_are_input_errors(kw, word):
    with pytest.raises(InputError, match=word):
        SfmOptions(**kw).validate()


def test_full_size_option_is_valid():
    SfmOptions(max_image_size=0).validate()


def test_cli_rejects_bad_sfm_option_before_any_work(tmp_path, capsys):
    from splattwin import io
    from splattwin.cli import main

    for i in range(2):
        io.write_image(tmp_path / "imgs" / f"{i}.png", np.zeros((20, 30, 3), np.uint8))
    rc = main(["poses", str(tmp_path / "imgs"), str(tmp_path / "out"), "--max-image-size", "8"])
    assert rc == 2 and "max-image-size" in capsys.readouterr().err
    assert not (tmp_path / "out" / "transforms.json").exists()


@pytest.mark.parametrize("poses_flag, build_flag, value", [
    ("--max-image-size", "--poses.max-image-size", "8"), ("--max-features", "--poses.max-num-features", "5"),
    ("--threads", "--poses.num-threads", "-2"), ("--min-registered", "--poses.min-registered", "1"),
    ("--marker-size", "--marker-size", "-0.05")])
def test_bad_pose_option_message_gives_both_commands_spelling(tmp_path, capsys, poses_flag, build_flag, value):
    """The same check serves `splattwin poses` and `build`, before any work; its message named only poses'
    flag (--max-image-size), which `build` does not have (--poses.max-image-size): it names both.
    `build` checked --min-registered and --marker-size not at all."""
    from splattwin import io
    from splattwin.cli import main

    for i in range(2):
        io.write_image(tmp_path / "imgs" / f"{i}.png", np.zeros((20, 30, 3), np.uint8))
    for argv in (["poses", str(tmp_path / "imgs"), str(tmp_path / "p"), poses_flag, value],
                 ["build", str(tmp_path / "imgs"), "--out", str(tmp_path / "b"), build_flag, value]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert poses_flag.replace("--max-features", "--max-num-features").replace("--threads", "--num-threads") \
            in err and build_flag in err and value in err, err
    assert not (tmp_path / "p").exists() and not (tmp_path / "b").exists()
    with pytest.raises(InputError, match="build: --poses.max-image-size"):
        SfmOptions(max_image_size=10).validate()   # the Python API's SfM options: the same message


# -- matcher ---------------------------------------------------------------------------------------------
def test_matcher_follows_capture_type():
    assert choose_matcher(9) == "exhaustive"                       # small unordered photo set
    assert choose_matcher(50) == "exhaustive"
    assert choose_matcher(51) == "retrieval"                       # large unordered: vocabulary-tree pairs
    # video frames: all pairs while few, as the help says (a short walk's loop closes); beyond, sequential
    assert choose_matcher(9, ordered=True) == "exhaustive"
    assert choose_matcher(50, ordered=True) == "exhaustive"
    assert choose_matcher(51, ordered=True) == "sequential"
    assert choose_matcher(400, ordered=True) == "sequential"
    assert choose_matcher(400, ordered=False, exhaustive_max_images=500) == "exhaustive"
    assert choose_matcher(400, "exhaustive", ordered=True) == "exhaustive"  # explicit choice wins
    with pytest.raises(InputError, match="matcher"):
        choose_matcher(5, "flann")


# -- threads and memory ----------------------------------------------------------------------------------
def test_extraction_threads_use_all_cores_within_the_memory_budget():
    assert extraction_threads(0, 1600, 2.0, cpu_count=16) == 16    # small scale space: every core
    few = extraction_threads(0, 3200, 2.0, cpu_count=16)            # upsampled 1600 px images
    assert 1 <= few < 16
    assert extraction_threads(0, 3200, 8.0, cpu_count=16) > few     # more memory, more threads
    assert extraction_threads(0, 20000, 2.0, cpu_count=16) == 1     # never zero
    assert extraction_threads(3, 800, 2.0, cpu_count=16) == 3       # an explicit count is an upper bound


def test_first_octave_skips_upsampling_only_for_large_images():
    assert first_octave(1600) == 0 and first_octave(1400) == 0
    assert first_octave(1060) == -1 and first_octave(683) == -1
    assert first_octave(1600, "more") == -1  # the more-features retry upsamples


# -- camera groups ---------------------------------------------------------------------------------------
def _jpeg(path: Path, w: int, h: int, exif: dict | None = None) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.new("RGB", (w, h), (120, 80, 40))
    if exif:
        ex = Image.Exif()
        ex[271], ex[272] = exif["make"], exif["model"]
        ex.get_ifd(0x8769)[37386] = exif["focal"]
        im.save(path, exif=ex)
    else:
        im.save(path)
    return path


def test_one_camera_per_size_and_exif_camera(tmp_path):
    paths = [_jpeg(tmp_path / "a.jpg", 64, 48), _jpeg(tmp_path / "b.jpg", 64, 48), _jpeg(tmp_path / "c.jpg", 48, 64),
             _jpeg(tmp_path / "d.jpg", 64, 48, {"make": "Acme", "model": "P1", "focal": 4.2}),
             _jpeg(tmp_path / "e.jpg", 64, 48, {"make": "Acme", "model": "P1", "focal": 4.2}),
             _jpeg(tmp_path / "f.jpg", 64, 48, {"make": "Acme", "model": "P1", "focal": 6.0})]
    names = [p.name for p in paths]
    groups = camera_groups(paths, names, SfmOptions())
    as_sets = sorted(sorted(g.names) for g in groups)
    assert as_sets == [["a.jpg", "b.jpg"], ["c.jpg"], ["d.jpg", "e.jpg"], ["f.jpg"]]
    g = next(g for g in groups if "d.jpg" in g.names)
    assert g.exif["make"] == "Acme" and g.exif["focal_mm"] == pytest.approx(4.2)
    # per-image cameras on request
    assert all(len(g.names) == 1 and g.per_image for g in camera_groups(paths, names, SfmOptions(shared_intrinsics=False)))
    # known intrinsics: one fixed camera, so one image size
    with pytest.raises(InputError, match="one image size"):
        camera_groups(paths, names, SfmOptions(intrinsics=(50.0, 50.0, 32.0, 24.0)))
    fixed = camera_groups(paths[:2], names[:2], SfmOptions(intrinsics=(50.0, 50.0, 32.0, 24.0)))
    assert len(fixed) == 1 and fixed[0].camera_model == "PINHOLE" and fixed[0].camera_params == [50.0, 50.0, 32.0, 24.0]


# -- retries ---------------------------------------------------------------------------------------------
def _groups(n=1, size=(640, 480), per_image=False):
    return [CameraGroup([f"{i}.jpg"], *size, per_image=per_image) for i in range(n)]


def test_retry_plan_cheapest_first():
    plan = retry_plan(_groups(), SfmOptions(), small_images=True, exif_focal=False)
    names = [a.name for a in plan]
    assert names == ["default", "relaxed", "guided", "more_features"]
    assert plan[1].features == "base" and plan[1].matching == "base" and plan[1].merge   # mapping only + merge
    assert plan[2].features == "base" and plan[2].matching == "guided"                    # same features
    assert plan[3].features == "more"                                                     # re-extract last
    # large images: the size bound already gave the features, no more-features retry
    assert "more_features" not in [a.name for a in retry_plan(_groups(), SfmOptions(), False, False)]
    # EXIF focal length: a retry holding it fixed; per-image cameras of one size: a shared-camera retry
    assert "exif_focal" in [a.name for a in retry_plan(_groups(), SfmOptions(), False, True)]
    shared = retry_plan(_groups(3, per_image=True), SfmOptions(shared_intrinsics=False), False, False)
    assert [a.cameras for a in shared if a.name == "shared_intrinsics"] == ["shared"]
    assert [a.name for a in retry_plan(_groups(), SfmOptions(retry=False), True, True)] == ["default"]


def test_relaxed_mapping_is_looser_than_default():
    d = mapping_options(SfmOptions(), 10, "default")
    r = mapping_options(SfmOptions(), 10, "relaxed")
    f = mapping_options(SfmOptions(), 10, "fixed_focal")
    for k in ("mapper.init_min_num_inliers", "mapper.abs_pose_min_num_inliers", "mapper.init_min_tri_angle"):
        assert r[k] < d[k]
    assert d.get("ba_refine_focal_length", True) and f["ba_refine_focal_length"] is False
    assert mapping_options(SfmOptions(intrinsics=(1, 1, 0, 0)), 10)["ba_refine_focal_length"] is False


def _outcome(reg: int) -> AttemptOutcome:
    return AttemptOutcome(rec=object() if reg else None, registered=reg, sub_models=[], db=None)


def test_retry_loop_stops_when_all_register_and_keeps_the_best():
    plan = [Attempt(n, n) for n in ("default", "relaxed", "guided", "more_features")]
    said, seen = [], []

    def execute(results):
        def run(a, i):
            seen.append(a.name)
            return _outcome(results[i])
        return run

    out, a = run_plan(plan, 8, execute([5, 8, 3, 8]), say=said.append)
    assert a.name == "relaxed" and out.registered == 8 and seen == ["default", "relaxed"]
    assert len(said) == 1 and "5/8" in said[0] and "relaxed" in plan[1].why
    seen.clear()
    out, a = run_plan(plan, 8, execute([5, 7, 7, 6]))  # never all: the best, the earlier on a tie
    assert a.name == "relaxed" and out.registered == 7 and seen == [p.name for p in plan]
    with pytest.raises(InputError, match="no initial image pair"):
        run_plan(plan, 8, execute([0, 0, 0, 0]))


def test_failure_reasons_from_the_match_graph():
    names = ["a", "b", "c", "d", "e", "f", "g", "h"]
    reg = {"a", "b", "c"}
    kp = {n: 2000 for n in names} | {"d": 12}
    verified = {("a", "b"): 300, ("b", "c"): 200, ("a", "e"): 40, ("f", "g"): 90, ("a", "h"): 5, ("c", "h"): 8}
    why = explain_failures(names, reg, kp, verified, min_inliers=12, sub_models=[{"f", "g", "x"}])
    assert set(why) == {"d", "e", "f", "g", "h"}
    assert "only 12 features" in why["d"]
    assert "40 inlier matches with a" in why["e"]
    assert "sub-model of 3 images" in why["f"]
    assert "no verified matches" in why["h"]  # 5 and 8 inliers: below the verification threshold
    why = explain_failures(names, reg, kp, verified, min_inliers=12)
    assert "matches only other unregistered images (g)" in why["f"]


def test_pair_ids_decode_like_colmap():
    import pycolmap

    from splattwin.poses.sfm import _MAX_IMAGE_ID

    for a, b in ((1, 2), (3, 7), (12, 70000)):
        assert divmod(pycolmap.image_pair_to_pair_id(a, b), _MAX_IMAGE_ID) == (a, b)
        assert divmod(pycolmap.image_pair_to_pair_id(b, a), _MAX_IMAGE_ID) == (a, b)


# -- progress --------------------------------------------------------------------------------------------
def test_plain_progress_lines_when_not_a_tty(monkeypatch):
    from splattwin.poses import progress as prog

    clock = [100.0]
    monkeypatch.setattr(prog.time, "monotonic", lambda: clock[0])
    buf = _io.StringIO()
    with prog.StageProgress(True, stream=buf, interval=5.0) as p:
        p.update("SfM: SIFT features", 0, 9)       # new stage: a line at once
        clock[0] += 1
        p.update("SfM: SIFT features", 3, 9)       # within the interval: no line
        clock[0] += 5
        p.tick()                                    # heartbeat after the interval
        p.update("SfM: matching", 0, 36)
        p.message("SfM: 5/8 images registered; retrying")
    lines = buf.getvalue().splitlines()
    assert lines == ["SfM: SIFT features: 0/9 (0 s)", "SfM: SIFT features: 3/9 (6 s)", "SfM: matching: 0/36 (0 s)",
                     "SfM: 5/8 images registered; retrying"]
    assert "\r" not in buf.getvalue() and "\x1b" not in buf.getvalue()
    # a stage that ended between lines gets its final count, before the next stage and at the end
    buf = _io.StringIO()
    with prog.StageProgress(True, stream=buf, interval=5.0) as p:
        p.update("SfM: SIFT features", 0, 9)
        clock[0] += 2
        p.update("SfM: SIFT features", 9, 9)
        p.update("SfM: matching", 0, 36)
        clock[0] += 3
        p.update("SfM: matching", 36, 36)
    assert buf.getvalue().splitlines() == ["SfM: SIFT features: 0/9 (0 s)", "SfM: SIFT features: 9/9 (2 s)",
                                           "SfM: matching: 0/36 (0 s)", "SfM: matching: 36/36 (3 s)"]
    # a one-off message (a retry starting) comes after the current stage's last count, not before it
    buf = _io.StringIO()
    with prog.StageProgress(True, stream=buf, interval=5.0) as p:
        p.update("SfM: incremental mapping", 1, 8)
        clock[0] += 1
        p.update("SfM: incremental mapping", 2, 8)
        p.message("SfM: 2/8 images registered; retrying with relaxed thresholds")
        p.update("SfM retry 1/3: SIFT features", 0, 8)
    assert buf.getvalue().splitlines() == ["SfM: incremental mapping: 1/8 (0 s)", "SfM: incremental mapping: 2/8 (1 s)",
                                           "SfM: 2/8 images registered; retrying with relaxed thresholds",
                                           "SfM retry 1/3: SIFT features: 0/8 (0 s)"]
    quiet = _io.StringIO()
    with prog.StageProgress(False, stream=quiet) as p:
        p.update("x", 1, 2)
        p.message("y")
    assert quiet.getvalue() == ""


def test_retry_loop_completes_the_best_model_from_other_attempts():
    plan = [Attempt(n, n) for n in ("default", "relaxed", "guided")]
    calls = []

    def complete(best, history):
        calls.append((best.registered, len(history)))
        return _outcome(8) if len(history) == 2 else None

    out, a = run_plan(plan, 8, lambda a, i: _outcome([3, 7, 7][i]), complete=complete)
    assert out.registered == 8 and a.name == "relaxed+merged" and calls == [(7, 2)]
    calls.clear()
    out, a = run_plan(plan, 8, lambda a, i: _outcome([3, 7, 6][i]), complete=lambda b, h: _outcome(5))
    assert out.registered == 7 and a.name == "relaxed"  # a worse completion is ignored


def test_retry_loop_recovers_before_the_next_retry_and_stops_when_all_are_back():
    plan = [Attempt(n, n) for n in ("default", "relaxed", "guided", "more_features")]
    seen, calls = [], []

    def execute(a, i):
        seen.append(a.name)
        return _outcome([2, 4, 6, 6][i])

    def recover(best, attempt):  # gives all 8 back once the best has 6 (the cake's guided model)
        calls.append((best.registered, attempt.name))
        return (_outcome(8), Attempt(attempt.name + "+recovered", "")) if best.registered == 6 else None

    out, a = run_plan(plan, 8, execute, recover=recover)
    assert out.registered == 8 and a.name == "guided+recovered"
    assert seen == ["default", "relaxed", "guided"]  # more_features not run
    assert calls == [(2, "default"), (4, "relaxed"), (6, "guided")]
    seen.clear()
    out, a = run_plan(plan, 8, execute, recover=lambda b, at: (_outcome(5), at))  # a worse result is ignored
    assert out.registered == 6 and a.name == "guided" and seen == [p.name for p in plan]


def test_too_few_registered_names_a_few_images_and_logs_each_reason(tmp_path, caplog):
    """A video whose SfM registered 15/30 frames gave a ~20 kB one-line error listing every frame with its
    reasons (audit 9 F13): the error names the count and the first few; the log has each one's reason."""
    import logging

    from splattwin.capture.camera import Camera
    from splattwin.poses.sfm import SfmResult, _check_enough

    cam = Camera(K=np.diag([100.0, 100.0, 1.0]), width=64, height=48, T_world_cam=np.eye(4))
    names = [f"frame_{i:05d}.png" for i in range(30)]
    res = SfmResult(cameras={n: cam for n in names[:15]}, unregistered=names[15:], points_xyz=np.zeros((0, 3)),
                    points_rgb=np.zeros((0, 3), np.uint8), points_error=np.zeros(0), points_track_len=np.zeros(0),
                    mean_reproj_error=0.0, failures={n: "its pose could not be estimated " * 20 for n in names[15:]})
    with caplog.at_level(logging.WARNING), pytest.raises(InputError) as e:
        _check_enough(res, SfmOptions(), tmp_path)
    msg = e.value.problem
    assert "registered only 15/30 images" in msg and "15 images (frame_00015.png, frame_00016.png, " \
        "frame_00017.png and 12 more" in msg and "frame_00018" not in msg and len(msg) < 1000
    assert "--poses.min-registered" in msg   # build's spelling beside poses'
    assert sum("not registered" in r.getMessage() for r in caplog.records) == 15
    # a few: each named with its reason, as before
    res.failures = {n: "no matches" for n in names[15:17]}
    res.unregistered = names[15:17]
    res.cameras = {n: cam for n in names[:2]}
    with pytest.raises(InputError, match="frame_00015.png: no matches; frame_00016.png: no matches"):
        _check_enough(res, SfmOptions(min_registered=3), tmp_path)


def test_progress_totals_count_every_matched_pair_and_never_show_more(monkeypatch):
    """60 video frames, sequential matching: the log said 639/600 (the total, 60 x 10, left out the
    loop-closure pairs the count includes), then mapping 60/60 before '30/60 images registered' (it sums
    the partial models) (audit 9 F16)."""
    from splattwin.poses import progress as prog
    from splattwin.poses.sfm import sequential_pairs

    # each frame with the next 10 (fewer at the end); every 10th with 30 look-alikes; the audit's database
    # of those 60 frames held 648 matched pairs
    assert sequential_pairs(60, 10, False) == 545
    assert sequential_pairs(60, 10, True) == 545 + 6 * 30 >= 648
    assert sequential_pairs(5, 10, False) == sequential_pairs(5, 10, True) == 10   # every pair, once
    monkeypatch.setattr(prog.time, "monotonic", lambda: 0.0)
    buf = _io.StringIO()
    with prog.StageProgress(True, stream=buf, interval=5.0) as p:
        p.update("SfM: sequential matching", 639, 600)   # an estimate too low still shows no overshoot
    assert buf.getvalue().splitlines() == ["SfM: sequential matching: 600/600 (0 s)"]
    said = []
    run_plan([Attempt("default", "default"), Attempt("relaxed", "relaxed")], 60,
             lambda a, i: _outcome([30, 60][i]), say=said.append)
    assert said == ["SfM: 30/60 images registered in the largest model; retrying with relaxed"]


def test_matching_and_mapping_steps_say_what_they_count(tmp_path, monkeypatch):
    """The totals the SfM steps run with: sequential matching with loop closure counts those pairs too;
    mapping says its count is of the images registered in all partial models (not the model kept)."""
    from splattwin.poses import colmap_process, sfm

    steps = []

    def fake_step(job, work, progress, label, total=1, poll_table=None, cleanup=None):
        steps.append((job["step"], label, total))
        return {"models": []}, colmap_process.StepStats(seconds=0.0, peak_rss_bytes=0, cpu_seconds=0.0)

    monkeypatch.setattr(colmap_process, "run_step", fake_step)
    names = [f"frame_{i:05d}.png" for i in range(60)]
    run = sfm.SfmRun(tmp_path, tmp_path, names, SfmOptions(ordered=True), progress=None,
                   groups=[CameraGroup(names, 64, 48)], matcher="sequential")
    a = Attempt("default", "default")
    run.match(run.db_path(a), a, "SfM")
    run.map(run.db_path(a), a, "SfM")
    assert steps[0] == ("match", "SfM: sequential matching", 725)
    assert steps[1][0] == "map" and "images registered, all partial models" in steps[1][1] and steps[1][2] == 60
