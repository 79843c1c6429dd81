"""splattwin.io: atomic writes."""

import os

import pytest

from splattwin import io
from splattwin.errors import InputError


def test_atomic_writes_have_normal_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        p = io.write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(umask)
    assert p.read_text() == "x" and (p.stat().st_mode & 0o777) == 0o644
    assert [f.name for f in tmp_path.iterdir()] == ["a.txt"]  # no temporary left behind


def test_failed_write_leaves_target_untouched(tmp_path):
    target = io.write_text(tmp_path / "b.json", "old")
    with pytest.raises(RuntimeError):
        with io.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old" and len(list(tmp_path.iterdir())) == 1


def test_read_json_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="file not found") as e:
        io.read_json(tmp_path / "none.json")
    assert e.value.path == tmp_path / "none.json"
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InputError, match="not valid JSON"):
        io.read_json(tmp_path / "bad.json")


def test_write_json_strict_writes_null_for_non_finite_floats(tmp_path):
    """The default: standard JSON (NaN/Infinity are not JSON; JSON.parse, jq and the viewer's browser refuse
    them), numpy included; strict=False keeps Python's tokens."""
    import json

    import numpy as np

    obj = {"a": float("nan"), "b": [1.5, float("inf"), np.float32("nan")], "c": np.array([1.0, -np.inf]),
           "d": (2, "x"), "e": None}
    p = io.write_json(tmp_path / "s.json", obj)

    def refuse(token):
        raise AssertionError(token)

    assert json.loads(p.read_text(), parse_constant=refuse) == {"a": None, "b": [1.5, None, None],
                                                                "c": [1.0, None], "d": [2, "x"], "e": None}
    assert "NaN" in io.write_json(tmp_path / "l.json", {"a": float("nan")}, strict=False).read_text()


def test_remove_stale_removes_only_gone_entries_and_never_follows_a_link(tmp_path):
    d = tmp_path / "objects"
    d.mkdir()
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.ply").write_text("x")
    for n in ("a.ply", "b.ply", "b.txt"):
        (d / n).write_text(n)
    (d / "c.ply").symlink_to(outside / "keep.ply")
    (d / "sub").mkdir()
    removed = io.remove_stale(d, {"a.ply"}, suffix=".ply")
    assert sorted(p.name for p in removed) == ["b.ply", "c.ply"]
    assert sorted(p.name for p in d.iterdir()) == ["a.ply", "b.txt", "sub"] and (outside / "keep.ply").is_file()
    (d / "gone").mkdir()
    (d / "gone" / "f").write_text("f")
    (d / "link").symlink_to(outside)
    assert [p.name for p in io.remove_stale(d, {"sub"}, dirs=True)] == ["gone"]
    assert (d / "link").is_symlink() and (outside / "keep.ply").is_file()


def test_read_record_is_none_for_a_missing_oversized_or_broken_record(tmp_path, monkeypatch):
    """io.read_record: the readers that go on without a record (report, headline, stale checks, SfM's work
    records) get None for one that is missing, over the record limit, not JSON or nested too deeply."""
    import json

    from splattwin import io, limits

    p = tmp_path / "r.json"
    assert io.read_record(p) is None
    p.write_text(json.dumps({"a": [1, 2]}))
    assert io.read_record(p) == {"a": [1, 2]}
    p.write_text("{not json")
    assert io.read_record(p) is None
    p.write_text("[" * 200 + "]" * 200)
    assert io.read_record(p) is None
    p.write_text(json.dumps({"pad": "x" * 5000}))
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 4000)
    assert io.read_record(p) is None
