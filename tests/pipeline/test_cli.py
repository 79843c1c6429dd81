from __future__ import annotations

import json

import pytest

from splattwin.pipeline.cli import _print_headline
from splattwin.pipeline.runner import Context


def test_headline_names_the_twin_only_when_there_is_one(tmp_path, capsys, monkeypatch):
    """`build --until splats` stops before the twin stage: the last line names the folder, not a twin.json."""
    monkeypatch.setenv("COLUMNS", "1000")   # rich: no wrapping inside the long tmp paths
    ctx = Context(out=tmp_path, options={}, timings={"poses": 8.0, "splats": 25.0},
                  results={"splats": {"gaussians": 7080, "split": "heldout", "psnr": 14.3, "ssim": 0.49}})
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "7080 Gaussians, heldout PSNR 14.30 dB" in out and "stage time, sum 33.0 s" in out
    assert "twin.json" in out and "no twin.json" in out and "twin: " not in out
    (tmp_path / "twin.json").write_text("{}")
    ctx.results["twin"] = {"manifest": "@twin.json"}
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert f"twin: {tmp_path / 'twin.json'}" in out and "no twin.json" not in out


def test_headline_names_only_stages_that_ran_or_are_recorded(tmp_path, capsys, monkeypatch):
    """`build --until splats` on a finished folder printed the earlier build's `semantics: held-out mIoU` and
    `twin: .../twin.json`, though neither stage ran (nor is recorded) this time."""
    import json

    monkeypatch.setenv("COLUMNS", "1000")
    (tmp_path / "semantics").mkdir()
    (tmp_path / "semantics" / "fusion.json").write_text(json.dumps({"miou_heldout": 0.49}))
    (tmp_path / "geometry_metrics.json").write_text(json.dumps({"cake": {"f1": 0.8}}))
    (tmp_path / "twin.json").write_text("{}")
    splats = {"gaussians": 39995, "split": "heldout", "psnr": 10.71, "ssim": 0.4}
    ctx = Context(out=tmp_path, options={}, timings={"poses": 1.0, "splats": 25.0},
                  results={"scene": {}, "poses": {}, "splats": splats})
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "39995 Gaussians" in out
    assert "mIoU" not in out and "F1" not in out and "twin: " not in out
    assert "twin.json there is from an earlier build: stages semantics..report did not run this time" in out
    ctx.results.update(semantics={}, twin={})     # the later stages ran (or were found up to date)
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "held-out mIoU 0.490" in out and "F1@5mm cake 0.800" in out and f"twin: {tmp_path / 'twin.json'}" in out


def test_the_reports_stage_list_is_the_pipelines():
    from splattwin.pipeline.options import STAGES
    from splattwin.report.build import PIPELINE_STAGES

    assert PIPELINE_STAGES == STAGES


def test_headline_total_is_what_this_run_took(tmp_path, capsys, monkeypatch):
    """A re-run that skipped every stage took 0.3 s: the total says so (it printed the skipped stages' old
    8 + 25 s as "total 33 s"); a run that redid some names those it skipped."""
    monkeypatch.setenv("COLUMNS", "1000")
    ctx = Context(out=tmp_path, options={}, timings={"poses": 8.0, "splats": 25.0}, skipped=["poses", "splats"],
                  wall_s=0.25)
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "total 0.2 s wall clock (all 2 stages up to date, skipped;" in out and "total 33" not in out
    ctx = Context(out=tmp_path, options={}, timings={"poses": 8.0, "splats": 25.0}, skipped=["poses"], wall_s=26.4)
    _print_headline(ctx)
    assert "total 26 s wall clock (1 of 2 stages up to date, skipped: poses;" in capsys.readouterr().out


def test_headline_total_and_the_reports_stage_time_are_labelled_and_share_one_figure(tmp_path, capsys, monkeypatch):
    """audit 7B D11: the terminal said "total 68 s" (wall clock, report included), the report "pipeline time
    (s) 48.5" (the stage records without the report), neither saying what it was. The terminal now says
    wall clock and gives the report's figure under the report's own name; the report explains both."""
    from splattwin.report.build import STAGE_TIME_KPI, build_report

    monkeypatch.setenv("COLUMNS", "1000")
    timings = {"scene": 0.5, "poses": 8.0, "splats": 30.0, "semantics": 4.0, "twin": 6.0}   # 48.5 s
    (tmp_path / "pipeline.json").write_text(json.dumps({k: {"seconds": v} for k, v in timings.items()}))
    page = build_report(tmp_path, timings=dict(timings), skipped=["scene", "poses"])
    ctx = Context(out=tmp_path, options={}, timings={**timings, "report": 15.0}, wall_s=68.2)
    _print_headline(ctx)
    out = " ".join(capsys.readouterr().out.split())
    assert "total 68 s wall clock, pre-flight and report included (the report's stage time, sum: 48.5 s)" in out
    import html as _html

    text = _html.unescape(page.read_text())
    assert f"{STAGE_TIME_KPI}" in text and "pipeline time" not in text
    assert "'stage time, sum' (48.5 s)" in text and "wall-clock time of that one run" in text
    assert text.count("up to date: an earlier build's seconds") == 2 and text.count(">this build<") == 3

def test_headline_of_a_build_stopped_before_the_report_says_there_is_none(tmp_path, capsys, monkeypatch):
    """`build photos/ --until splats` (the build a capture without masks can make) ended "total 355 s wall
    clock, pre-flight and report included (the report's stage time, sum: 355.2 s)", but wrote no report."""
    monkeypatch.setenv("COLUMNS", "1000")
    ctx = Context(out=tmp_path, options={}, timings={"scene": 0.1, "poses": 24.0, "splats": 331.1}, wall_s=355.4)
    _print_headline(ctx)
    out = " ".join(capsys.readouterr().out.split())
    assert "report included" not in out, out
    assert "total 355 s wall clock, pre-flight included (stage time, sum: 355.2 s; no report" in out
    assert f"splattwin report {tmp_path}" in out


def test_run_stages_records_what_it_skipped_and_its_own_time(tmp_path):
    from splattwin.pipeline.runner import Stage, run_stages

    def slow(ctx):
        import time
        time.sleep(0.3)
        return {}

    stages = [Stage("a", slow), Stage("b", lambda ctx: {})]
    first = run_stages(stages, Context(tmp_path, {}))
    assert first.skipped == [] and first.wall_s >= 0.3
    again = run_stages(stages, Context(tmp_path, {}))
    assert again.skipped == ["a", "b"] and again.wall_s < 0.3 <= again.timings["a"]


def test_headline_and_exit_code_say_whether_real_arm_files_were_written(tmp_path, capsys, monkeypatch):
    """A robot run whose real-arm files were refused (FR3 limits, or objects moved before the robot acted)
    printed "robot task: success" and exited 0 while `plan` exits 2: build now exits 2 and says why, once;
    a validated run names robot/program.json."""
    import json

    from splattwin.pipeline.cli import _exit_code

    monkeypatch.setenv("COLUMNS", "1000")
    (tmp_path / "robot").mkdir()
    reason = "the trajectory leaves the FR3's joint limits (--joint-names fr3; ...): fr3_joint1 at t = 0.010 s"
    (tmp_path / "robot" / "results.json").write_text(json.dumps({"real_robot": {"written": False, "reason": reason}}))
    ctx = Context(out=tmp_path, options={}, timings={"robot": 3.0},
                  results={"robot": {"results": "@robot/results.json", "success": True, "error": None,
                                     "export_error": reason}})
    _print_headline(ctx)
    out = " ".join(capsys.readouterr().out.split())
    assert "robot task: success in simulation, but no files for the real arm" in out
    assert out.count("fr3_joint1 at t = 0.010 s") == 1 and _exit_code(ctx) == 2
    (tmp_path / "robot" / "results.json").write_text(json.dumps({"real_robot": {"written": True, "reason": None}}))
    ctx.results["robot"]["export_error"] = None
    _print_headline(ctx)
    out = " ".join(capsys.readouterr().out.split())
    assert f"robot task: success; real arm: {tmp_path / 'robot' / 'program.json'}" in out and _exit_code(ctx) == 0
    (tmp_path / "robot" / "results.json").write_text(json.dumps({"real_robot": {
        "written": False, "reason": "the task failed in the validation run at step 2 (bottle): no transit"}}))
    ctx.results["robot"]["success"] = False
    _print_headline(ctx)
    out = " ".join(capsys.readouterr().out.split())
    assert "robot task: failure, no files for the real arm: the task failed" in out and _exit_code(ctx) == 1


def test_headline_says_when_psnr_is_over_loss_masked_pixels(tmp_path, capsys, monkeypatch):
    import json

    monkeypatch.setenv("COLUMNS", "1000")
    (tmp_path / "splat" / "eval").mkdir(parents=True)
    (tmp_path / "splat" / "eval" / "metrics.json").write_text(json.dumps({"loss_masks": {"applied": True}}))
    ctx = Context(out=tmp_path, options={}, timings={"splats": 1.0},
                  results={"splats": {"gaussians": 7080, "split": "heldout", "psnr": 26.64, "ssim": 0.9}})
    _print_headline(ctx)
    assert "heldout PSNR 26.64 dB, SSIM 0.9000 (over loss-masked pixels)" in capsys.readouterr().out
    (tmp_path / "splat" / "eval" / "metrics.json").write_text(json.dumps({"loss_masks": {"applied": False}}))
    _print_headline(ctx)
    assert "masked" not in capsys.readouterr().out


def test_build_into_the_captures_own_folder_is_refused_before_anything(tmp_path, capsys):
    """`build photos --out photos` (or a transforms.json's folder) exits 2 naming the folder, writing nothing:
    the twin's folders and records would be mixed with the photos (its pictures then read as photos in
    sub-folders; removing the twin removes the capture). A twin folder inside the capture's is accepted."""
    import numpy as np
    from PIL import Image

    from splattwin.cli import main
    from splattwin.errors import InputError
    from splattwin.pipeline.build import check_output
    from splattwin.pipeline.options import BuildOptions

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * i, np.uint8)).save(photos / f"{i}.png")
    before = sorted(p.name for p in photos.iterdir())
    for args in ([str(photos), "--out", str(photos)], [str(photos), "--out", str(photos / ".." / "photos")]):
        assert main(["build", *args, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert "capture's own folder" in err and str(photos) in err
        assert sorted(p.name for p in photos.iterdir()) == before   # nothing written (no lock, no records)
    (photos / "transforms.json").write_text("{}")
    opts = BuildOptions(input=str(photos / "transforms.json"))
    with pytest.raises(InputError, match="capture's own folder"):
        check_output(photos, opts)
    check_output(photos / "twin", opts)                            # inside the capture: fine
    check_output(tmp_path / "twin", BuildOptions(input=str(photos)))


def test_headline_reads_a_twins_records_bounded_and_skips_malformed_ones(tmp_path, capsys, monkeypatch):
    """An up-to-date stage is skipped, so the headline may read a received twin's records: a fusion.json that is
    a list raised AttributeError (an internal error after a finished build), and every record was read whole
    whatever its size. Now each is read within the record limit and left out of the headline when it is not
    a readable JSON object."""
    import json

    import splattwin.limits as limits

    monkeypatch.setenv("COLUMNS", "1000")
    (tmp_path / "semantics").mkdir()
    (tmp_path / "semantics" / "fusion.json").write_text(json.dumps([1, 2]))
    (tmp_path / "geometry_metrics.json").write_text(json.dumps({"box": {"f1": 0.987}, "pad": "x" * 5000}))
    ctx = Context(out=tmp_path, options={}, timings={"semantics": 1.0, "twin": 1.0},
                  results={"semantics": {}, "twin": {}})
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 4000)
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "semantics:" not in out and "geometry:" not in out
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 1 << 20)
    (tmp_path / "geometry_metrics.json").write_text(json.dumps({"box": {"f1": 0.987}}))
    (tmp_path / "semantics" / "fusion.json").write_text(json.dumps({"miou_heldout": 0.912}))
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "semantics: held-out mIoU 0.912" in out and "geometry: F1@5mm box 0.987" in out
