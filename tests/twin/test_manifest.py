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
