"""splattwin.poses.twin_frame: a received frame.json is checked like twin.json's frame."""

from __future__ import annotations

import json

import pytest

from splattwin.errors import InputError
from splattwin.poses.twin_frame import TwinFrame, load_frame


@pytest.mark.parametrize("text, needle", [
    ('{"source": "marker", "scaled": "false"}', "scaled must be true or false"),  # truthy text: read as metric
    ('[1, 2]', "expected a JSON object"),
    ('{"source": "marker", "scaled": true', "not valid JSON"),
])
def test_malformed_frame_json_names_the_file(tmp_path, text, needle):
    p = tmp_path / "frame.json"
    p.write_text(text)
    with pytest.raises(InputError, match=needle) as e:
        load_frame(tmp_path)
    assert e.value.path == p


def test_frame_json_has_the_record_size_limit(tmp_path, monkeypatch):
    from splattwin import limits

    p = tmp_path / "frame.json"
    p.write_text(json.dumps({"source": "marker", "scaled": True, "description": "x" * 2000}))
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 1000)
    with pytest.raises(InputError, match="limit") as e:
        load_frame(p)
    assert e.value.path == p


def test_summary_says_each_fact_once():
    """Headers printed "frame: unscaled (UNSCALED, unscaled, up +z)": the source, the scale and the units all said
    "unscaled". Now once, with what the lengths are."""
    assert TwinFrame(source="unscaled", scaled=False).summary() == "unscaled (SfM units; up +z)"
    assert TwinFrame(source="marker", scaled=True, units="m").summary() == "marker (metric, metres; up +z)"
    # a source that names no scale, without one: the summary still says the lengths are not metres
    assert TwinFrame(source="known_poses", scaled=False).summary() == "known_poses (not metric; up +z)"
