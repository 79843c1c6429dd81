import json

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses.twin_frame import TwinFrame
from splattwin.twin.manifest import Background, Manifest, ObjectEntry


def test_round_trip_and_lookup(tmp_path):
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.03]
    m = Manifest(frame=TwinFrame("marker", True, scale_uncertainty_rel=0.01),
                 objects=[ObjectEntry("box", 1, "blue box", T_world_obj=T.tolist(), mass=0.2),
                          ObjectEntry("ghost", 2, usable=False, problem="missing label")],
                 background=Background(table_height=0.0), timings={"geometry.mesh": 1.5})
    m.save(tmp_path)
    back = Manifest.load(tmp_path)
    assert back.to_dict() == m.to_dict()
    assert np.allclose(back.object("box").pose, T)
    with pytest.raises(InputError, match="no object named"):
        back.object("nope")


def test_bad_manifests_raise_input_error(tmp_path):
    with pytest.raises(InputError, match="no twin manifest"):
        Manifest.load(tmp_path)
    (tmp_path / "twin.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        Manifest.load(tmp_path)
    (tmp_path / "twin.json").write_text(json.dumps({"schema_version": 99}))
    with pytest.raises(InputError, match="schema_version"):
        Manifest.load(tmp_path)
    (tmp_path / "twin.json").write_text(json.dumps({"schema_version": 1, "objects": [{"name": "a"}]}))
    with pytest.raises(InputError, match="malformed"):
        Manifest.load(tmp_path)


def test_frame_records_the_input_world_and_is_checked(tmp_path):
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    m = Manifest(frame=TwinFrame("known_poses", True, T_twin_input=F.tolist(), up_check={"input_up": "-z"}))
    m.save(tmp_path)
    back = Manifest.load(tmp_path)
    assert np.array_equal(back.frame.T_twin_input, F) and back.frame.up_check == {"input_up": "-z"}
    d = json.loads((tmp_path / "twin.json").read_text())
    d["frame"]["T_twin_input"] = [[1, 0], [0, 1]]
    (tmp_path / "twin.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match="frame T_twin_input must be a finite 4x4"):
        Manifest.load(tmp_path)


def _saved(tmp_path, edit):
    """A valid twin.json in tmp_path, edited as raw JSON (as a received file would be)."""
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.03]
    Manifest(frame=TwinFrame("marker", True), objects=[ObjectEntry("box", 1, T_world_obj=T.tolist(), mass=0.2,
                                                                   bbox_extent=[0.1, 0.1, 0.05])]).save(tmp_path)
    d = json.loads((tmp_path / "twin.json").read_text())
    edit(d)
    (tmp_path / "twin.json").write_text(json.dumps(d))
    return tmp_path


def _set(path, value):
    def edit(d):
        *keys, last = path
        for k in keys:
            d = d[k]
        d[last] = value
    return edit


@pytest.mark.parametrize("path, value, needle", [
    (("background", "table_extent"), [-1e300, 1e300, -1e300, 1e300], "table_extent"),   # MJCF MuJoCo cannot load
    (("background", "table_extent"), [0.5, 0.5, -0.4, 0.4], "table_extent"),           # zero-width table box
    (("background", "table_extent"), [0.5, -0.5, -0.4, 0.4], "table_extent"),
    (("background", "table_thickness"), 0.0, "table_thickness"),
    (("background", "table_thickness"), 1e30, "table_thickness"),
    (("background", "table_height"), -1e9, "table_height"),
    (("objects", 0, "bbox_extent"), [0.1, 1e12, 0.1], "bbox_extent"),
    (("objects", 0, "mass"), 1e300, "mass"),
    (("objects", 0, "volume"), -1.0, "volume"),
    (("objects", 0, "silhouette_coverage"), 1.5, "silhouette_coverage"),      # a share of the masks
    (("objects", 0, "silhouette_precision"), "high", "silhouette_precision"),
    (("objects", 0, "T_world_obj"), [[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "T_world_obj"),
    (("objects", 0, "T_world_obj"), [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]], "rigid"),
    (("objects", 0, "T_world_obj"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 5, 1]], "rigid"),
    (("frame", "nominal_metre"), 1e300, "nominal_metre"),
    (("frame", "nominal_metre"), 0.0, "nominal_metre"),
    (("frame", "T_twin_input"), [[1e300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "T_twin_input"),
    (("exports",), {"mjcf": 5}, "export 'mjcf'"),
    # wrong types that Python's truthiness or True == 1 let through (a metric-looking unscaled twin)
    (("frame", "scaled"), "false", "scaled must be true or false"),
    (("frame", "source"), 123, "source must be text"),
    (("objects", 0, "usable"), "false", "usable must be true or false"),
    (("objects", 0, "prompt"), {"a": 1}, "prompt must be text"),
    (("objects", 0, "problem"), [1], "problem must be text"),
    (("schema_version",), True, "schema_version"),
    # labels index 16-bit label images and per-label tables (a palette of 1.5e9 colours took 9 GB)
    (("objects", 0, "label"), 1_500_000_000, r"label .* \[1, 65535\]"),
    (("objects", 0, "label"), 10**30, r"label .* \[1, 65535\]"),
])
def test_absurd_numbers_are_refused_naming_twin_json(tmp_path, path, value, needle):
    twin = _saved(tmp_path, _set(path, value))
    with pytest.raises(InputError, match=needle) as e:
        Manifest.load(twin)
    assert e.value.path == twin / "twin.json"


def test_big_twin_json_is_refused_and_errors_stay_short(tmp_path, monkeypatch):
    """twin.json was read under the 1 GiB limit for COCO files (a 300 MB padded list took 3 GB), and the
    error turned the whole padded list into text before cutting it."""
    from splattwin import limits
    from splattwin.twin import manifest

    twin = _saved(tmp_path, _set(("objects", 0, "bbox_extent"), [0.0] * 200_000))
    with pytest.raises(InputError, match="bbox_extent") as e:
        Manifest.load(twin)
    assert len(str(e.value)) < 400
    assert manifest.MAX_RECORD_BYTES == limits.MAX_RECORD_BYTES <= 64 << 20
    monkeypatch.setattr(manifest, "MAX_RECORD_BYTES", 100_000)   # the file is ~1 MB
    with pytest.raises(InputError, match="limit") as e:
        Manifest.load(twin)
    assert e.value.path == twin / "twin.json"


def test_unscaled_twin_sizes_are_within_bounds(tmp_path):
    # an unscaled twin (SfM units) can be hundreds of units across: the bounds must not refuse it
    def edit(d):
        d["frame"] = {"source": "unscaled", "scaled": False, "nominal_metre": 350.0}
        d["background"]["table_extent"] = [-800.0, 900.0, -650.0, 700.0]
        d["background"]["table_height"] = -120.0
        d["background"]["table_thickness"] = 10.5
        o = d["objects"][0]
        o["T_world_obj"][0][3] = 420.0
        o["bbox_extent"] = [70.0, 55.0, 40.0]
        o["volume"] = 154000.0
    m = Manifest.load(_saved(tmp_path, edit))
    assert m.background.table_extent[1] == 900.0 and m.frame.nominal_metre == 350.0


@pytest.mark.parametrize("key", ["splats", "labels", "collision_mesh", "export"])
def test_escaping_path_error_names_the_twin_folder(tmp_path, key):
    def edit(d):
        if key == "collision_mesh":
            d["objects"][0]["collision_mesh"] = "../../etc/passwd"
        elif key == "export":
            d["exports"]["mjcf"] = "../../etc/passwd"
        else:
            d[key] = "../../etc/passwd"
    (tmp_path / "twin").mkdir()
    twin = _saved(tmp_path / "twin", edit)
    with pytest.raises(InputError, match="leads outside") as e:
        Manifest.load(twin)
    assert e.value.path == twin / "twin.json"
    assert f"its folder {twin} " in str(e.value) and "nonexistent" not in str(e.value)
    # without a folder (a manifest from a dict), the folder of the file named
    d = json.loads((twin / "twin.json").read_text())
    with pytest.raises(InputError, match=f"outside its folder {tmp_path}") as e:
        Manifest.from_dict(d, tmp_path / "twin.json")
    assert "nonexistent" not in str(e.value)


def test_load_takes_the_twin_folder_or_its_twin_json(tmp_path):
    """`Manifest.load("TWIN/twin.json")` looked for TWIN/twin.json/twin.json (audit 10A L2); TwinFrame.load
    and PoseResult.load already take the folder or the file."""
    (tmp_path / "objects").mkdir()
    m = Manifest(objects=[ObjectEntry("cup", 1, splat_ply="objects/cup.ply")])
    m.save(tmp_path)
    assert Manifest.load(tmp_path / "twin.json") == Manifest.load(tmp_path) == m
    with pytest.raises(InputError, match=r"nothing[/\\]twin.json: no twin manifest"):
        Manifest.load(tmp_path / "nothing" / "twin.json")
    (tmp_path / "escape").mkdir()
    bad = Manifest(objects=[ObjectEntry("cup", 1, splat_ply="../objects/cup.ply")]).to_dict()
    (tmp_path / "escape" / "twin.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match="outside|leaves|inside"):   # paths still confined to the file's folder
        Manifest.load(tmp_path / "escape" / "twin.json")


def test_a_build_folder_without_a_twin_says_the_build_stopped_before_the_twin(tmp_path):
    """`splattwin export`, `plan` and `view` on the folder of `build --until splats` (the only build a capture
    without masks can make) said "no twin manifest here (expected twin.json)", as for any wrong folder. A
    build folder now says the build stopped before the twin stage and that masks make the twin."""
    (tmp_path / "splat").mkdir()
    (tmp_path / "splat" / "point_cloud.ply").write_bytes(b"ply\n")
    (tmp_path / "pipeline.json").write_text("{}")
    with pytest.raises(InputError, match="no twin manifest here") as e:
        Manifest.load(tmp_path)
    assert "stopped before the twin stage" in str(e.value) and "--masks" in str(e.value)
    (tmp_path / "other").mkdir()
    with pytest.raises(InputError, match="no twin manifest") as e:
        Manifest.load(tmp_path / "other")
    assert "stopped before" not in str(e.value)


def test_render_filter_says_how_the_twins_splats_were_trained(tmp_path):
    """Rendering a twin's splats from Python drew them with the classic 0.3 px^2 filter whatever they were
    trained with (`make demo`: antialiased), and the reader of the trained filter was private to playback (api13
    B3). Manifest.render_filter() gives (rasterize_mode, eps2d) for render_rgb / rasterization."""
    from splattwin.playback.scene import manifest_filter

    m = Manifest()
    assert m.render_filter() == ("classic", 0.3)
    m.config = {"build": {"splat": {"rasterize_mode": "antialiased", "eps2d": 0.0}}}
    assert m.render_filter() == manifest_filter(m) == ("antialiased", 0.1)
    m.config["build"]["splat"]["eps2d"] = 0.2
    assert m.render_filter() == ("antialiased", 0.2)
    m.config["build"]["splat"]["rasterize_mode"] = "fancy"
    with pytest.raises(InputError, match=r"twin\.json: config\.build\.splat: unknown rasterize_mode 'fancy'"):
        m.render_filter()
