"""Readers found failing by a systematic fuzz pass over a received twin folder (each of its files truncated,
randomised, given wrong JSON types, huge header counts, paths out of the folder): each case here ended in a
traceback of an internal error (CLI exit 1) before its fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _report_twin(tmp_path: Path, test_module) -> Path:
    """A twin with a manifest, eval metrics and robot results of this twin (report/test_build.py's helpers)."""
    from splattwin.robot.outputs import twin_digest

    helpers = test_module("report/test_build.py")
    twin = helpers._manifest_twin(tmp_path, scaled=True)
    helpers._robot_results(twin, twin_digest(twin))
    return twin


@pytest.mark.parametrize("rel, edit, needle", [
    # found: geometry_metrics.json {"cardboard_box": [0, 1, 2, ...]} -> TypeError in the summary's F1 figure
    ("geometry_metrics.json", lambda d: {"cake": [0, 1, 2]}, "geometry_metrics.json is malformed"),
    # found: metrics.json mean_psnr {} -> TypeError in round()
    ("splat/eval/metrics.json", lambda d: {**d, "mean_psnr": {}}, "splat/eval/metrics.json is malformed"),
    ("semantics/fusion.json", lambda d: {"miou_heldout": "x"}, "semantics/fusion.json is malformed"),
    ("robot/results.json", lambda d: {**d, "trials": {"successes": 1}}, "robot/results.json is malformed"),
    ("robot/results.json", lambda d: {**d, "nominal": []}, "robot/results.json is malformed"),
    # a record that is no JSON object at all is left out as unreadable
    ("geometry_metrics.json", lambda d: ["f1"], None),
])
def test_report_summary_of_malformed_records_notes_the_file(tmp_path, test_module, cli, rel, edit, needle):
    """The summary's figures came from the records unguarded (the sections below it are guarded): a received
    twin's record of the wrong shape failed the whole report with an internal error. Now that record's figures
    are left out with a note naming the file; the rest of the report is written."""
    twin = _report_twin(tmp_path, test_module)
    path = twin / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    before = json.loads(path.read_text()) if path.is_file() else {}
    path.write_text(json.dumps(edit(before)))
    res = cli("report", twin, "--no-video")
    assert res.rc == 0, res.err[-2000:]
    html = (twin / "report" / "index.html").read_text()
    assert "Summary" in html and "Collision geometry" in html
    if needle:
        assert needle in html
