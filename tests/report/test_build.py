"""The report names the held-out views, their rule and the evaluation resolution (from the artifacts)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from splattwin.report.build import build_report

_spec = importlib.util.spec_from_file_location("_report_trainer_helpers",
                                               Path(__file__).parents[1] / "splat" / "test_trainer.py")
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def _twin(tmp_path: Path, **metrics) -> Path:
    """A twin folder with a 3+2-view capture and the eval metrics given (plus the required ones)."""
    twin = tmp_path / "twin"
    helpers.make_dataset(twin / "poses", n_train=3, n_heldout=2)
    (twin / "splat" / "eval").mkdir(parents=True)
    (twin / "splat" / "eval" / "metrics.json").write_text(json.dumps({
        "split": "heldout", "mean_psnr": 24.5, "mean_ssim": 0.81, "n_views": 2, "gaussians": 1234, **metrics}))
    return twin


def test_report_shows_heldout_views_and_eval_resolution(tmp_path):
    twin = _twin(tmp_path, **{
        "eval_resolution": {"mode": "training", "how": "auto: longest side at most 640 px on the CPU",
                            "sizes": "640x480", "full_sizes": "4032x3024", "scale": 0.1587},
        "heldout": {"rule": "every 8th view from the first (default with >= 6 views)", "source": "default",
                    "views": ["heldout_003", "heldout_004"]},
        "views": [{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}, {"name": "heldout_004", "psnr": 25.0,
                                                                         "ssim": 0.82}]})
    html = build_report(twin).read_text()
    assert "640x480 (the training resolution)" in html and "4032x3024" in html
    assert "every 8th view from the first" in html
    assert "heldout_003, heldout_004" in html
    assert "3 training views and 2 held-out views" in html


def test_report_shows_the_transient_masks_when_training_wrote_them(tmp_path):
    import numpy as np

    from splattwin.io import write_image

    twin = _twin(tmp_path, views=[{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}])
    assert "transient masks" not in build_report(twin).read_text()
    write_image(twin / "splat" / "transients.png", np.zeros((20, 30, 3), np.uint8))
    assert "transient masks (red)" in build_report(twin).read_text()


def test_report_takes_training_and_evaluation_resolution_each_from_its_own_record(tmp_path):
    # trained at --resolution 2, evaluated at full size (--eval-full-resolution): the audit's statue
    twin = _twin(tmp_path, eval_resolution={"mode": "full", "how": "full size", "sizes": "1080x1920",
                                            "full_sizes": "1080x1920", "scale": 1.0},
                 views=[{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}])
    (twin / "splat" / "train.json").write_text(json.dumps(
        {"resolution": {"resolution": 2, "max_side": None, "how": "--resolution 2"}}))
    html = build_report(twin).read_text()
    assert "<td>training resolution rule</td><td>--resolution 2</td>" in html.replace("\n", "")
    assert "<td>evaluation resolution rule</td><td>full size</td>" in html.replace("\n", "")


def _manifest_twin(tmp_path: Path, scaled: bool, table_default: str | None = None) -> Path:
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import Background, Manifest, ObjectEntry

    twin = _twin(tmp_path, views=[{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}])
    frame = TwinFrame(source="known_poses" if scaled else "unscaled", scaled=scaled, nominal_metre=None if scaled else 6.49)
    Manifest(frame=frame, objects=[ObjectEntry(name="cake", label=1, bbox_extent=[1.143, 0.736, 1.354])],
             background=Background(table_extent=[-4.61, 1.88, -5.18, 0.01], table_default=table_default)).save(twin)
    return twin


def test_report_shows_an_unscaled_twins_lengths_in_units_never_cm(tmp_path):
    html = build_report(_manifest_twin(tmp_path, scaled=False, table_default="no table splats")).read_text()
    assert "1.14 × 0.736 × 1.35 units (SfM, unscaled)" in html
    assert "114.3" not in html and " cm" not in html
    # the assumed table is said so, in the twin's units
    assert "WARNING: the table is assumed (no table splats)" in html
    assert "x -4.61 .. 1.88 units (SfM, unscaled)" in html


def test_report_shows_a_metric_twins_box_in_cm_and_no_table_warning_when_found(tmp_path):
    html = build_report(_manifest_twin(tmp_path / "m", scaled=True)).read_text()
    assert "114.3 × 73.6 × 135.4 cm" in html
    assert "the table is assumed" not in html


def test_report_shows_the_robot_options_that_made_the_results_not_the_twin_stage_s(tmp_path):
    """A build re-run with `--task default --trials 3` skips the twin stage: twin.json's config.build.robot
    still says trials 0. The report's options show those of the run in robot/results.json."""
    from splattwin.twin.manifest import Manifest

    twin = _manifest_twin(tmp_path, scaled=True)
    man = Manifest.load(twin)
    man.config["build"] = {"robot": {"task": None, "trials": 0}, "geometry": {"min_points": 50}}
    man.save(twin)
    from splattwin.robot.outputs import twin_digest

    (twin / "robot").mkdir()
    (twin / "robot" / "results.json").write_text(json.dumps({
        "error": "no usable object", "task": "default", "options": {"task": "default", "trials": 3, "seed": 5},
        "twin_digest": twin_digest(twin)}))
    import html as htmllib

    html = htmllib.unescape(build_report(twin).read_text())
    assert "(from robot/results.json)" in html and '"trials": 3' in html and '"trials": 0' not in html
    assert '"min_points": 50' in html


def test_report_shows_each_objects_silhouette_coverage(tmp_path):
    """The geometry table's "masks covered" column: the share twin.json records, n/a when not measured; a
    usable object's problem (a warning) is shown too."""
    from splattwin.twin.manifest import Manifest, ObjectEntry

    twin = _manifest_twin(tmp_path, scaled=True)
    man = Manifest.load(twin)
    man.objects[0].silhouette_coverage = 0.973
    man.objects.append(ObjectEntry(name="shard", label=man.objects[0].label + 1, silhouette_coverage=0.21,
                                   problem="possibly incomplete: its splats cover 21% of its 2D masks' silhouettes"))
    man.objects.append(ObjectEntry(name="unmeasured", label=man.objects[0].label + 2))
    man.save(twin)
    import html as htmllib

    html = htmllib.unescape(build_report(twin).read_text())
    assert "masks covered" in html and "97%" in html and "21%" in html and "possibly incomplete" in html
    assert html.count("n/a") >= 1


def _robot_results(twin: Path, digest) -> None:
    (twin / "robot").mkdir(exist_ok=True)
    step = {"index": 1, "pick": "cake", "goal": "region", "grasped": True, "placed": True, "at_rest": True,
            "robot_collisions": 0, "object_collisions": 0, "success": True, "failure": None}
    (twin / "robot" / "results.json").write_text(json.dumps({
        "task": "task.yaml", "planner": "rrt", "nominal": {"success": True, "steps": [step]},
        "trials": {"successes": 2, "trials": 2, "sigma": 0.005, "ci95": [0.3, 1.0], "collisions": 0},
        **({"twin_digest": digest} if digest is not None else {})}))


def test_report_shows_no_robot_results_of_another_twin(tmp_path):
    """robot/ of a `plan` on an earlier twin (rebuilt since, e.g. the object renamed): the report showed
    its task, steps and trials as this twin's. Now a note says why they are not shown."""
    from splattwin.robot.outputs import twin_digest
    from splattwin.twin.manifest import Manifest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    html = build_report(twin).read_text()
    assert "robustness: 2/2 trials" in html and "task success" in html
    man = Manifest.load(twin)            # the twin rebuilt: its object renamed
    man.objects[0].name = "dessert"
    man.save(twin)
    html = build_report(twin).read_text()
    assert "robustness" not in html and "task success" not in html and "<td>cake</td>" not in html
    assert "no robot results shown" in html and "earlier state of this twin" in html
    _robot_results(twin, None)           # an earlier splattwin's results: cannot be checked, not shown
    html = build_report(twin).read_text()
    assert "robustness" not in html and "no twin digest" in html


def test_report_warns_when_pipeline_json_does_not_vouch_for_the_twin(tmp_path, caplog):
    """`build --until splats` (or a build stopped after poses) keeps the earlier semantics/ and twin.json: the
    report showed them beside the new splats with no word. pipeline.json recording no semantics/twin stage
    now gives a warning, in the log and the report; a complete record, or no pipeline.json, none."""
    twin = _manifest_twin(tmp_path, scaled=True)
    (twin / "semantics").mkdir()
    (twin / "semantics" / "fusion.json").write_text(json.dumps({"options": {"kappa": 1.5, "iters": 3}, "objects": []}))
    assert "earlier build" not in build_report(twin).read_text()          # no pipeline.json: stages run by hand
    rec = {"key": "k", "outputs": {}, "seconds": 1.0}
    (twin / "pipeline.json").write_text(json.dumps({n: rec for n in ("scene", "poses", "splats")}))
    with caplog.at_level("WARNING"):
        html = build_report(twin).read_text()
    note = ("semantics/fusion.json, twin.json are from an earlier build: stages semantics..report did not run "
            "after the last splats")
    assert note in html and note in caplog.text
    (twin / "pipeline.json").write_text(json.dumps({n: rec for n in ("scene", "poses")}))   # Ctrl-C in training
    assert "stages splats..report did not run after the last poses" in build_report(twin).read_text()
    (twin / "pipeline.json").write_text(json.dumps({n: rec for n in ("scene", "poses", "splats", "semantics",
                                                                         "twin", "robot", "report")}))
    assert "earlier build" not in build_report(twin).read_text()


def test_report_warns_when_a_stages_recorded_outputs_were_rewritten(tmp_path, caplog):
    """`splattwin train TWIN/poses/transforms.json TWIN/splat` run by hand into a built twin rewrites
    splat/point_cloud.ply: the report showed the earlier splat's held-out PSNR (and semantics and meshes
    fused from it) with no word, because pipeline.json had a record of every stage. The recorded output
    digests no longer match: a warning naming the stage and the file, in the log and the report."""
    from splattwin.hashing import DigestCache, output_digests

    twin = _manifest_twin(tmp_path, scaled=True)
    (twin / "splat" / "point_cloud.ply").write_bytes(b"the built splat")
    outputs = {"splats": {"ply": "@splat/point_cloud.ply"}, "twin": {"manifest": "@twin.json"}}
    state = {n: {"key": "k", "seconds": 1.0, "outputs": outputs.get(n, {}),
                 "digests": output_digests(twin, outputs.get(n, {}), DigestCache())}
             for n in ("scene", "poses", "splats", "semantics", "twin", "robot", "report")}
    (twin / "pipeline.json").write_text(json.dumps(state))
    html = build_report(twin).read_text()
    assert "no longer match" not in html                        # every recorded output as recorded
    (twin / "splat" / "point_cloud.ply").write_bytes(b"a splat trained by hand")
    with caplog.at_level("WARNING"):
        html = build_report(twin).read_text()
    note = "splat/point_cloud.ply (stage splats) no longer matches what the build recorded"
    assert note in caplog.text and f"WARNING: {note}" in html
    assert "stages splats..twin shown here (held-out metrics, semantics, twin)" in html


def test_a_splats_only_report_names_the_poses_frame(tmp_path):
    """`build --until splats` leaves no twin.json: the header said "frame: n/a" for an unscaled capture."""
    from splattwin import io
    from splattwin.poses.twin_frame import TwinFrame

    twin = _twin(tmp_path, **{"views": [{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8}]})
    assert not (twin / "twin.json").exists()
    io.write_json(twin / "poses" / "frame.json", vars(TwinFrame(source="unscaled", scaled=False)))
    html = build_report(twin).read_text()
    # each fact once: it said "frame: unscaled (UNSCALED, unscaled, up +z)"
    assert "frame: unscaled (SfM units; up +z)" in html and "frame: n/a" not in html


def _obstacle_twin(tmp_path: Path) -> Path:
    from splattwin.twin.manifest import Manifest, ObjectEntry

    twin = _manifest_twin(tmp_path, scaled=True)
    man = Manifest.load(twin)
    T = [[1, 0, 0, 0.0], [0, 1, 0, 0.0], [0, 0, 1, 0.05], [0, 0, 0, 1]]
    man.objects.append(ObjectEntry(name="yellow_cube", label=2, usable=False, obstacle_only=True, T_world_obj=T,
                                   bbox_extent=[0.1, 0.1, 0.1], problem="too few points after cleaning (41 < 50)"))
    man.save(twin)
    return twin


def test_report_says_an_obstacle_only_object_is_kept_as_a_static_box(tmp_path):
    """audit 6b D2: the collision table said only "usable: no"; the box is in every export and the
    robot's world, and the report says so."""
    import html as htmllib

    html = htmllib.unescape(build_report(_obstacle_twin(tmp_path)).read_text())
    assert "no: obstacle-only box (estimate)" in html
    assert ("too few points after cleaning (41 < 50); kept as a static obstacle box (an estimate of its extent) "
            "that the robot avoids: it cannot be picked or placed on" in html)


def test_report_pictures_draw_the_obstacle_box_translucent_red(tmp_path):
    import numpy as np

    from splattwin.report.build import _twin_meshes, render_meshes

    meshes = _twin_meshes(_obstacle_twin(tmp_path))
    assert len(meshes) == 1 and meshes[0][3] == 0.5 and meshes[0][2][0] > 0.8 > 0.4 > meshes[0][2][1]
    # a camera 1 m above looking down: the box over a grey floor is a blend of both, the floor elsewhere
    floor = (np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]),
             (0.5, 0.5, 0.5))
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = [0, 0, 1.0]
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    img = render_meshes([floor] + meshes, T, K, 64, 64)
    centre, edge = img[32, 32], img[2, 2]
    assert centre[0] > centre[1] + 0.1                     # reddish: the box is drawn
    assert abs(edge[0] - edge[1]) < 1e-6                   # grey floor beside it
    # translucent: half the opaque box's colour, half the floor's under it
    solid = render_meshes([floor, meshes[0][:3]], T, K, 64, 64)[32, 32]
    bare = render_meshes([floor], T, K, 64, 64)[32, 32]
    np.testing.assert_allclose(centre, 0.5 * solid + 0.5 * bare, atol=1e-5)
    assert not np.allclose(centre, solid, atol=0.05)


def test_report_shows_what_the_run_gives_the_real_arm(tmp_path):
    """The robot section showed task, steps and trials only: now the real-arm block (files written or why
    not, program phases, exported joint names, base frame and pose, limit check, tracking error, start
    check); a run whose objects moved before the robot acted says it is no validation of the twin."""
    from splattwin.robot.outputs import twin_digest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    res = json.loads((twin / "robot" / "results.json").read_text())
    res.update(joint_names={"exported": [f"fr3_joint{i}" for i in range(1, 8)], "simulated": []},
               base_frame="fr3_link0", base_pose={"x": -0.5, "y": 0.0, "z": 0.0, "yaw": 0.0},
               tracking={"joint_max_rad": 0.00286, "tcp_max_m": 0.00348, "tcp_median_m": 0.00039},
               real_robot={"written": True, "reason": None, "files": ["program.json"], "limits_checked": "FR3 doc"},
               settle={"time_s": 0.5, "threshold_m": 0.01, "threshold_deg": 5.0, "moved": [],
                       "objects": {"cake": {"moved_m": 0.0002, "turned_deg": 0.1, "dz_m": 0.0}}})
    (twin / "robot" / "results.json").write_text(json.dumps(res))
    (twin / "robot" / "program.json").write_text(json.dumps({"phases": [
        {"kind": k} for k in ("gripper", "arm", "gripper", "arm", "gripper", "arm")]}))
    html = build_report(twin).read_text()
    for s in ("real-arm files", "written: robot/program.json", "6: 3 arm, 3 gripper", "fr3_joint1 .. fr3_joint7",
              "fr3_link0", "x -0.5, y 0.0, z 0.0 m", "base_transform.yaml", "checked, inside (FR3 doc)",
              "TCP max 3.48 mm, median 0.39 mm", "start check", "passed"):
        assert s in html, s
    reason = "the twin is not at rest in physics: before the robot acted, cake moved 5.0 cm (fell)"
    res.update(real_robot={"written": False, "reason": reason, "files": []},
               notes=[f"no trajectory for the real arm: {reason}"],
               settle={**res["settle"], "moved": ["cake"],
                       "objects": {"cake": {"moved_m": 0.05, "turned_deg": 0.0, "dz_m": -0.05}}})
    (twin / "robot" / "results.json").write_text(json.dumps(res))
    html = build_report(twin).read_text()
    assert "NOT a validation of the twin" in html and "NOT written: the twin is not at rest" in html
    assert "FAILED: cake moved" in html and html.count("cake moved 5.0 cm (fell)") == 1


def test_report_shows_the_sfm_reprojection_error_and_time(tmp_path):
    """poses_report.json writes `mean_reproj_error` and `timings`; the report looked up
    `mean_reproj_error_px` and `sfm_s`, so an SfM twin's table showed neither."""
    twin = _twin(tmp_path)
    (twin / "poses" / "poses_report.json").write_text(json.dumps({
        "method": "sfm", "total": 15, "registered": 15, "mean_reproj_error": 0.38120204642600397,
        "num_points": 314, "timings": {"extract": 0.819, "cpu": 1.827, "match": 0.675, "map": 0.474}}))
    html = build_report(twin).read_text()
    assert "mean reprojection error (px)" in html and "0.381" in html and "314" in html
    assert "SfM time (s): extract, match, map" in html and "1.97" in html


def test_report_labels_loss_masked_metrics_and_says_images_once(tmp_path):
    """Held-out PSNR/SSIM over loss-masked pixels were shown as if over whole images, and the legend
    stored in metrics.json (beginning "images:") was printed after "Images:"."""
    lm = {"applied": True, "views": ["heldout_000", "heldout_001"], "protocol": "pixels a frame's mask_path "
          "sets to 0 are left out."}
    import html as _html

    twin = _twin(tmp_path, loss_masks=lm, legend="images: ground truth | render | error", views=[])
    html = _html.unescape(build_report(twin).read_text())
    assert "PSNR heldout, masked (dB)" in html and "(masked: over the pixels the capture's loss masks keep)" in html
    assert "loss masks applied (nerfstudio mask_path) to 2 evaluated views: heldout_000" in html
    assert "Images: images:" not in html and "Images: ground truth | render | error." in html
    (twin / "splat" / "eval" / "metrics.json").write_text(json.dumps({
        "split": "heldout", "mean_psnr": 24.5, "mean_ssim": 0.81, "n_views": 2, "gaussians": 1234, "views": []}))
    assert "masked" not in build_report(twin).read_text()


def test_report_shows_the_scale_from_the_depth_images(tmp_path):
    """The report showed a bare 'scale uncertainty (rel.) 0.01' for a depth-scaled SfM twin: no factor,
    readings or spread; and a header 'z +z'."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import Manifest

    twin = _manifest_twin(tmp_path, scaled=True)
    man = Manifest.load(twin)
    man.frame = TwinFrame(source="table_plane+depth", scaled=True, scale_uncertainty_rel=0.0100006,
                          description="table frame; metric scale from the depth images")
    man.save(twin)
    (twin / "poses" / "poses_report.json").write_text(json.dumps({
        "method": "sfm", "depth_scale": {"scale": 0.0758097, "spread_rel": 0.00712, "uncertainty_rel": 0.0100006,
                                         "readings": 6206, "views": 12}}))
    html = build_report(twin).read_text().replace("\n", "")
    assert "x 0.0758097 (SfM unit -&gt; m), 6206 readings over 12 views, spread 0.71 %" in html
    assert "<td>scale uncertainty (1 sigma)</td><td>1 %</td>" in html
    assert "metric scale from the depth images" in html and "z +z" not in html


def test_report_shows_the_exposure_check_and_the_appearance_decision(tmp_path):
    """The poses stage's exposure check (spread, images beyond the threshold) and the splat stage's
    appearance decision (train.json) are shown; before, a capture with differing exposures said nothing."""
    import html as _html

    twin = _twin(tmp_path, views=[])
    (twin / "poses" / "poses_report.json").write_text(json.dumps({
        "method": "known", "total": 5, "registered": 5,
        "exposure": {"spread_pct": 41.25, "threshold_pct": 10.0, "varies": True, "images_off": ["view_002"]}}))
    (twin / "splat" / "train.json").write_text(json.dumps({"appearance": {
        "requested": "auto", "mode": "gain", "decision": "auto", "spread_pct": 41.25, "init": "measured",
        "init_views": 4}}))
    html = _html.unescape(build_report(twin).read_text())
    assert "gains differ by up to 41.2 % (threshold 10.0 %); beyond it: view_002" in html
    assert "appearance): gain (turned on by --splat.appearance auto" in html
    assert "started at the poses stage's measured gains (4 views)" in html
    (twin / "poses" / "poses_report.json").write_text(json.dumps({
        "method": "known", "exposure": {"error": "no sparse points to compare the images on"}}))
    (twin / "splat" / "train.json").write_text(json.dumps({"appearance": {"mode": "off", "decision": "suggested"}}))
    html = _html.unescape(build_report(twin).read_text())
    assert "not measured: no sparse points" in html and "off (although the poses stage found" in html


def test_report_shows_the_label_maps_of_this_fusions_views_only(tmp_path):
    """The report globbed semantics/label_maps/*.png: a map left by an earlier build of other views was
    shown as this twin's (audit 9 F12). It shows the views fusion.json lists."""
    import numpy as np

    from splattwin.io import write_image

    twin = _twin(tmp_path)
    sem = twin / "semantics"
    for sub in ("label_maps", "masks_vs_labels"):
        for view in ("heldout_003", "heldout_009"):
            write_image(sem / sub / f"{view}.png", np.zeros((20, 30, 3), np.uint8))
    (sem / "fusion.json").write_text(json.dumps({"options": {"kappa": 1.5, "iters": 3}, "objects": [],
                                                 "label_map_views": ["train_000", "heldout_003"]}))
    html = build_report(twin).read_text()
    # heldout_003 is the capture's held-out view: its masks were not fused (audit 11G)
    assert "heldout_003: fused labels rendered" in html and "heldout_003: 2D masks (held-out view" in html
    assert "heldout_009" not in html


def test_a_missing_twin_folder_is_bad_input_not_a_new_report(tmp_path: Path):
    """build_report("typo") created typo/report/index.html, an empty report of nothing, and a file path
    raised NotADirectoryError (audit 10A L14); the command checked the folder, the function did not."""
    import pytest

    from splattwin.errors import InputError

    with pytest.raises(InputError, match="twin folder does not exist"):
        build_report(tmp_path / "typo")
    assert not (tmp_path / "typo").exists()
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(InputError, match="a_file: twin folder does not exist"):
        build_report(tmp_path / "a_file")


def test_an_unscaled_twins_robot_section_says_why_there_is_no_plan(tmp_path):
    """The robot section of an unscaled twin told the user to run `splattwin plan`, which refuses it."""
    html = build_report(_manifest_twin(tmp_path, scaled=False)).read_text()
    robot = html.split("Robot task in physics")[1].split("</section>")[0]
    assert "no robot plan: the twin is unscaled" in robot and "--known-length" in robot
    assert "splattwin plan TWIN, or build with --task" not in robot
    metric = build_report(_manifest_twin(tmp_path / "m", scaled=True)).read_text()
    assert "no robot task run (splattwin plan TWIN, or build with --task)" in metric


def _embedded(html: str) -> dict:
    """{caption: (MIME type, picture bytes)} of the report's embedded pictures."""
    import base64
    import re

    return {m.group(3): (m.group(1), base64.b64decode(m.group(2)))
            for m in re.finditer(r'src="data:(image/[a-z]+);base64,([^"]*)" alt="([^"]*)"', html)}


def _figures(html: str) -> dict:
    """{caption: (width, height)} of the report's embedded pictures (PNG or JPEG)."""
    import io as _io

    from PIL import Image

    return {cap: Image.open(_io.BytesIO(data)).size for cap, (_, data) in _embedded(html).items()}


def test_report_embeds_photographic_pictures_as_jpeg_and_the_camera_plot_as_png(tmp_path):
    """Every picture was a PNG: the demo twin's report was 5.7 MB. The photos, renders and
    photo | render | error strips are JPEG now; the camera plot stays PNG (thin lines and text)."""
    import numpy as np

    from splattwin.capture import load_dataset, load_image
    from splattwin.io import write_image
    from splattwin.pictures import side_by_side

    twin = _twin(tmp_path, views=[{"name": "heldout_003", "psnr": 24.0, "ssim": 0.8, "image": "heldout_003.png"}])
    photo = load_image(load_dataset(twin / "poses" / "transforms.json", validate=False).frames[3].image_path)
    strip = side_by_side([photo, photo, np.zeros_like(photo)])
    write_image(twin / "splat" / "eval" / "heldout_003.png", (strip * 255 + 0.5).astype(np.uint8))
    write_image(twin / "poses" / "cameras.png", (strip * 255 + 0.5).astype(np.uint8))   # many colours
    pics = _embedded(build_report(twin).read_text())
    assert pics["a few input views"][0] == "image/jpeg"
    assert pics["heldout_003: ground truth | render | error"][0] == "image/jpeg"
    assert pics["camera poses and sparse points"] == ("image/png", (twin / "poses" / "cameras.png").read_bytes())


def test_report_input_views_are_thumbnails_not_the_full_size_photos(tmp_path):
    """The cake/statue report embedded 4 photos at full size side by side (the statue: 4336x1920)."""
    from splattwin.report.build import THUMB_HEIGHT

    twin = tmp_path / "twin"
    helpers.make_dataset(twin / "poses", n_train=4, n_heldout=1, width=640, height=480)
    w, h = _figures(build_report(twin).read_text())["a few input views"]
    assert h == THUMB_HEIGHT and w < 4 * 640 * THUMB_HEIGHT / 480 + 4 * 4


def test_report_collision_pictures_show_the_photo_beside_the_meshes_with_a_colour_key(tmp_path):
    """The collision pictures were the meshes alone, unnamed, without a key: a failed placement's text
    ("see its collision mesh in the report") sent the user to pictures where no object could be told apart,
    nor compared with what the camera saw."""
    import numpy as np

    from splattwin.capture import load_dataset
    from splattwin.report.build import _collision_views, _twin_meshes

    twin = _obstacle_twin(tmp_path)
    ds = load_dataset(twin / "poses" / "transforms.json", validate=False)
    cam = ds.frames[0].camera
    figs = {c: wh for c, wh in _figures(build_report(twin).read_text()).items() if "collision geometry" in c}
    assert len(figs) == 3 and all(c.split(":")[0] in {f.name for f in ds.frames} for c in figs)
    # photo | render | key, each at the camera's size
    assert all(wh[0] == 2 * cam.width + 140 + 8 and wh[1] >= cam.height for wh in figs.values())
    name, pic = _collision_views(twin, ds.frames[:1])[0]
    key = pic[:, 2 * cam.width + 8:]
    swatch = tuple(round(255 * c) for c in _twin_meshes(twin)[0][2])   # the obstacle box's colour
    key = np.round(np.asarray(key, np.float64) * 255).astype(int)   # side_by_side: float in [0, 1]
    assert (np.abs(key - swatch).max(axis=-1) <= 1).any()


def test_report_label_maps_mark_a_real_captures_held_out_view(tmp_path):
    """The label maps were picked and marked held-out by "heldout" in the file name: a real capture's
    held-out view (the cake's frame000020) was shown as "frame000020: fused labels rendered" among the
    training views' maps, which repeat the masks-vs-labels pictures above them."""
    import numpy as np

    from splattwin.io import write_image

    twin = _twin(tmp_path)
    sem = twin / "semantics"
    views = ["frame000020", "frame000069", "frame000096"]
    for view in views:
        write_image(sem / "label_maps" / f"{view}.png", np.zeros((20, 30, 3), np.uint8))
    (sem / "fusion.json").write_text(json.dumps({"options": {"kappa": 1.5, "iters": 3}, "objects": [],
                                                 "label_map_views": views,
                                                 "miou_heldout_masks_views": ["frame000020"]}))
    html = build_report(twin).read_text()
    assert "frame000020: fused labels rendered (held-out view: not used by the fusion)" in html
    assert "frame000069: fused labels rendered" not in html


def test_report_trial_statistics_say_what_was_perturbed_and_what_the_interval_is_of(tmp_path):
    """"robustness: 3/3 trials at σ = 5.0 mm (95 % CI 0.44–1.00)": σ of what, an interval of what, and the
    trials' yaw error (2.9°) not said at all."""
    import html as htmllib

    from splattwin.robot.outputs import twin_digest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    res = json.loads((twin / "robot" / "results.json").read_text())
    res["trials"] = {"trials": 3, "successes": 3, "success_rate": 1.0, "ci95": [0.4385, 1.0], "sigma": 0.005,
                     "sigma_yaw": 0.05, "collisions": 1}
    (twin / "robot" / "results.json").write_text(json.dumps(res))
    html = htmllib.unescape(build_report(twin).read_text())
    assert ("3/3 trials succeeded, each with every object's x and y position perturbed by σ = 5.0 mm per axis "
            "and its yaw by σ = 2.9°") in html
    assert "success rate 1.00, 95 % confidence interval 0.44–1.00; 1 collision in all trials" in html


def test_report_says_what_measured_depth_carving_dropped_and_by_which_rule(tmp_path):
    """twin.json config.depth_carving was shown as "cardboard_box 1779 of 59493 points (15 views)": not
    what happened to them, nor the share or the tolerance that decided it."""
    import html as htmllib

    from splattwin.twin.manifest import Manifest

    twin = _manifest_twin(tmp_path, scaled=True)
    man = Manifest.load(twin)
    man.config = {**(man.config or {}), "depth_carving": {
        "used": True, "tolerance": 0.002, "noise_1m": 0.005, "erode_px": 2,
        "objects": {"cardboard_box": {"views": 15, "points": 59493, "dropped": 1779},
                    "yellow_cube": {"views": 1, "points": 1640, "dropped": 338}}}}
    man.save(twin)
    html = htmllib.unescape(build_report(twin).read_text())
    assert ("a depth camera saw through were dropped as free space (more than 2.0 mm + 5.0 mm × z² in front of "
            "the measured depth z in m, inside the object's mask eroded by 2 px): cardboard_box 1779 of 59493 "
            "points (3.0 %, 15 depth views), yellow_cube 338 of 1640 points (20.6 %, 1 depth view).") in html


def test_report_says_a_failed_run_stopped_at_its_failed_step(tmp_path):
    """A 2-step task whose step 1 failed showed a step table of one row, read as the whole task: the
    executor stops at the first failed step."""
    from splattwin.robot.outputs import twin_digest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    html = build_report(twin).read_text()
    assert "the run stopped at the failed step" not in html
    res = json.loads((twin / "robot" / "results.json").read_text())
    res["nominal"]["success"] = False
    res["nominal"]["steps"][0].update(success=False, placed=False, failure="'cake' tipped over")
    (twin / "robot" / "results.json").write_text(json.dumps(res))
    html = build_report(twin).read_text()
    assert "the run stopped at the failed step 1: the task&#x27;s later steps, if any, were not attempted" in html


def test_an_unscaled_twins_options_say_which_lengths_are_sfm_units(tmp_path):
    """The unscaled cake's options block showed geometry.needle_length 0.0389 and build.geometry.needle_length
    0.006 side by side, bare: the first in SfM units, the second in metres, nothing said."""
    import html as htmllib

    from splattwin.twin.manifest import Manifest

    for scaled in (False, True):
        twin = _manifest_twin(tmp_path / str(scaled), scaled=scaled)
        man = Manifest.load(twin)
        man.config = {"geometry": {"needle_length": 0.0389}, "build": {"geometry": {"needle_length": 0.006}}}
        man.save(twin)
        html = htmllib.unescape(build_report(twin).read_text())
        said = ("in the twin's SfM units (the metre values given, under \"build\" → \"geometry\", times the nominal "
                "metre 6.49 units)") in html
        assert said != scaled


def test_report_real_arm_row_points_to_the_failed_steps_note_instead_of_repeating_it(tmp_path):
    """The robot section showed a failed placement's 400-character text in the step table and again, word
    for word, in the real-arm row right below it."""
    import html as htmllib

    from splattwin.robot.outputs import twin_digest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    res = json.loads((twin / "robot" / "results.json").read_text())
    why = ("'cake' tipped over: it ended tilted 90 deg (upright means within 10 deg); not on 'plate': 4.2 cm below "
           "the height of resting on it")
    res["nominal"]["success"] = False
    res["nominal"]["steps"][0].update(success=False, placed=False, failure=why)
    res["real_robot"] = {"written": False, "files": [],
                         "reason": f"the task failed in the validation run at step 1 (cake): {why}"}
    (twin / "robot" / "results.json").write_text(json.dumps(res))
    html = htmllib.unescape(build_report(twin).read_text())
    assert html.count(why) == 1
    assert "NOT written: the task failed in the validation run at step 1 (cake): see step 1's note above" in html


def test_report_names_the_steps_a_failed_run_did_not_attempt(tmp_path):
    """A failed run's report said "the task's later steps, if any, were not attempted": results.json held
    only the steps that ran. With `nominal.task_steps` it names them; a results.json without it (an
    earlier splattwin) keeps the old sentence."""
    import html as htmllib

    from splattwin.robot.outputs import twin_digest

    twin = _manifest_twin(tmp_path, scaled=True)
    _robot_results(twin, twin_digest(twin))
    res = json.loads((twin / "robot" / "results.json").read_text())
    ok = res["nominal"]["steps"][0]
    failed = {**ok, "index": 2, "pick": "mug", "goal": "tray", "placed": False, "success": False,
              "failure": "'mug' tipped over"}
    res["nominal"] = {"success": False, "steps": [ok, failed]}

    def robot_section() -> str:
        (twin / "robot" / "results.json").write_text(json.dumps(res))
        page = htmllib.unescape(build_report(twin).read_text())
        return page.split("Robot task in physics")[1].split("</section>")[0]

    assert "the run stopped at the failed step 2: the task's later steps, if any, were not attempted." \
        in robot_section()
    res["nominal"]["task_steps"] = [
        {"index": 1, "pick": "cake", "goal": "region", "place": "in"},
        {"index": 2, "pick": "mug", "goal": "tray", "place": "on"},
        {"index": 3, "pick": "cup", "goal": "mug", "place": "on"},
        {"index": 4, "pick": "spoon", "goal": "bin", "place": "in"}]
    robot = robot_section()
    assert "the run stopped at the failed step 2 of 4: steps 3-4 (cup on mug, spoon in bin) were not attempted." \
        in robot
    assert "<td>3</td><td>cup</td><td>mug</td>" in robot and robot.count("not attempted</td>") == 2
    res["nominal"]["task_steps"] = res["nominal"]["task_steps"][:3]
    assert "step 3 (cup on mug) was not attempted." in robot_section()
    res["nominal"]["task_steps"] = res["nominal"]["task_steps"][:2]
    assert "the run stopped at the failed step 2, the task's last." in robot_section()
    res["nominal"]["task_steps"] = [{"index": "2"}]     # malformed: as if not recorded
    assert "the task's later steps, if any, were not attempted." in robot_section()
