"""The issue's smaller promises: the viewer warns on non-loopback addresses and says when the asked port
was busy; writes are fsync'd before the rename; folders get ordinary permissions; `splattwin geometry
X.ply --out T` with default options succeeds (an unscaled twin: every export but MJCF); messages of
wrong-size masks name the file that is wrong."""

from __future__ import annotations

import os
import socket
import stat
import warnings
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.errors import InputError

from security_helpers import assert_bad_input


@pytest.fixture(scope="module")
def gt_twin(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_minor") / "twin"
    twin_from_scene(scene_small, out)
    return out


def test_viewer_warns_on_public_host_and_busy_port(gt_twin, caplog):
    import logging

    caplog.set_level(logging.WARNING, logger="splattwin.viewer")
    from splattwin.viewer.app import is_loopback, serve

    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5") and not is_loopback("myhost")
    server = serve(gt_twin, host="0.0.0.0", port=0, block=False)
    server.stop()
    err = caplog.text
    assert "WARNING" in err and "not on loopback" in err and "no authentication" in err
    caplog.clear()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        server = serve(gt_twin, host="127.0.0.1", port=port, block=False)
        try:
            got = server.get_port()
        finally:
            server.stop()
    err = caplog.text
    assert got != port and f"port {port} was busy" in err and f"port {got}" in err
    caplog.clear()
    server = serve(gt_twin, host="127.0.0.1", port=0, block=False)
    server.stop()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_fsync_before_rename(tmp_path, monkeypatch):
    calls = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))),
                                                 real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (calls.append(("replace", str(b))), real_replace(a, b))[1])
    io.write_text(tmp_path / "a.json", "{}")
    kinds = [k for k, _ in calls]
    first_replace = kinds.index("replace")
    assert "fsync" in kinds[:first_replace], calls                       # the data, before the rename
    assert ".a.json.tmp" in calls[kinds.index("fsync")][1]
    assert ("fsync", str(tmp_path)) in calls[first_replace:]             # then the folder entry


def test_parts_folders_have_ordinary_permissions(tmp_path):
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.twin.build import build_twin
    from splattwin.poses.twin_frame import TwinFrame

    g, labels, objects, _ = synthetic_scene(3000, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = build_twin(g, labels, objects, tmp_path / "t", TwinFrame("ground_truth", True), formats=(), progress=False)
    umask = os.umask(0)
    os.umask(umask)
    parts = [tmp_path / "t" / Path(o.convex_parts[0]).parent for o in m.objects if o.convex_parts]
    assert parts
    for p in parts:
        assert stat.S_IMODE(p.stat().st_mode) == 0o777 & ~umask, oct(p.stat().st_mode)
        for f in p.iterdir():
            assert stat.S_IMODE(f.stat().st_mode) & 0o644 == 0o644 & ~umask


def test_geometry_with_default_options_succeeds(tmp_path, cli):
    """`splattwin geometry X.ply --out T`: the default frame is unscaled; every export is written (MJCF
    included, issue #16), each marked unscaled, and a re-export does the same; an unknown format is refused
    before anything is written."""
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.twin.manifest import Manifest

    g, _, _, _ = synthetic_scene(3000, seed=4)
    ply = g.save_ply(tmp_path / "scan.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = cli("geometry", ply, "--out", tmp_path / "T")
    assert res.rc == 0, res.err[-2000:]
    assert "the twin is unscaled" in res.out
    m = Manifest.load(tmp_path / "T")
    assert not m.frame.scaled and m.frame.units == "unscaled" and set(m.exports) == {"mjcf", "urdf", "moveit", "gltf"}
    assert "UNSCALED" in (tmp_path / "T" / "export" / "scene.xml").read_text()
    assert cli("export", tmp_path / "T").rc == 0            # the same default for a re-export
    assert "UNSCALED" in (tmp_path / "T" / "export" / "scene.urdf").read_text()
    res = cli("geometry", ply, "--out", tmp_path / "T2", "--formats", "sdf")
    assert_bad_input(res, "--formats", "unknown export format")
    assert not (tmp_path / "T2" / "twin.json").exists()


def test_wrong_size_mask_blames_its_own_file(tmp_path):
    from splattwin.semantics.masks import load_masks

    ok = np.zeros((6, 8), np.uint8)
    io.write_image(tmp_path / "m" / "v0" / "aaa.png", np.zeros((5, 5), np.uint8))   # wrong, read first
    io.write_image(tmp_path / "m" / "v0" / "bbb.png", ok)
    with pytest.raises(InputError) as e:
        load_masks(tmp_path / "m", image_sizes={"v0": (6, 8)})
    assert e.value.path.name == "aaa.png" and "5x5" in e.value.problem and "8x6" in e.value.problem
    with pytest.raises(InputError) as e:   # without the image sizes: both files are named
        load_masks(tmp_path / "m")
    assert e.value.path.name == "bbb.png" and "aaa.png" in e.value.problem
