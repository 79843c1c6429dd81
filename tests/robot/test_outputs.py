"""robot/results.json records the twin it was made on (`twin_digest`), so results of an earlier twin are
told apart (`results_twin`): the report shows none and the pipeline removes them."""

from __future__ import annotations

import json
from pathlib import Path

import trimesh

from splattwin.robot.outputs import results_twin, twin_digest


def small_twin(folder: Path, name: str = "cake", size: float = 0.1) -> Path:
    """A metric twin.json with one usable object and its collision mesh (no splats)."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.twin.manifest import Background, Manifest, ObjectEntry

    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / "objects" / name / "collision.obj"
    mesh.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[size] * 3).export(mesh)
    Manifest(frame=TwinFrame("known_poses", scaled=True),
             objects=[ObjectEntry(name=name, label=1, usable=True, bbox_extent=[size] * 3,
                                  collision_mesh=f"objects/{name}/collision.obj",
                                  convex_parts=[f"objects/{name}/collision.obj"])],
             background=Background(table_extent=[-0.5, 0.5, -0.5, 0.5])).save(folder)
    return folder


def test_twin_digest_follows_the_objects_and_meshes_not_the_timings(tmp_path):
    from splattwin.twin.manifest import Manifest

    twin = small_twin(tmp_path / "t")
    d0 = twin_digest(twin)
    assert d0 is not None and d0 == twin_digest(twin)
    man = Manifest.load(twin)            # a deterministic rebuild: other run times, exports, build options
    man.timings["geometry"] = 12.3
    man.exports = {}
    man.config["build"] = {"splat": {"iters": 7}}
    man.save(twin)
    assert twin_digest(twin) == d0
    small_twin(twin, size=0.2)           # other meshes, same names
    assert twin_digest(twin) != d0
    other = small_twin(tmp_path / "o", name="dessert")
    assert twin_digest(other) != twin_digest(small_twin(tmp_path / "c"))
    assert twin_digest(tmp_path / "none") is None


def test_results_twin_says_why_results_are_not_this_twins(tmp_path):
    twin = small_twin(tmp_path / "t")
    assert results_twin({"twin_digest": twin_digest(twin), "nominal": {}}, twin) is None
    assert "earlier state of this twin" in results_twin({"twin_digest": "0" * 64}, twin)
    assert "no twin digest" in results_twin({"nominal": {}}, twin)     # an earlier splattwin's results
    assert "unreadable" in results_twin(None, twin)


def test_error_results_record_the_twin_too(tmp_path):
    """results.json of a task that could not run (an unscaled twin) is this twin's result too."""
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.robot.options import RobotOptions
    from splattwin.robot.stage import RobotInputs, run
    from splattwin.twin.manifest import Manifest

    twin = small_twin(tmp_path / "t")
    man = Manifest.load(twin)
    man.frame = TwinFrame("unscaled", scaled=False, nominal_metre=5.0)
    man.save(twin)
    res = run(RobotInputs(twin, twin / "robot"), RobotOptions(task="default"), progress=False, record_errors=True)
    doc = json.loads(res.results.read_text())
    assert "error" in doc and doc["twin_digest"] == twin_digest(twin)
    assert results_twin(doc, twin) is None
