from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.twin.groundtruth import twin_from_scene
from splattwin.twin.manifest import Manifest
from splattwin.twin.mjcf import build_spec, export_mjcf


@pytest.fixture(scope="module")
def twin(scene_small: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("twin_mjcf")
    twin_from_scene(scene_small, out)
    return out


def test_export_loads_and_objects_rest(twin: Path):
    path = export_mjcf(twin)
    assert path == twin / "export" / "scene.xml"
    assert 'file="../objects/' in path.read_text()          # relative: the twin folder can move
    assert Manifest.load(twin).exports["mjcf"] == "export/scene.xml"
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    manifest = Manifest.load(twin)
    names = [o.name for o in manifest.objects if o.usable]
    assert m.nbody == 1 + len(names)
    mujoco.mj_forward(m, d)
    p0 = {n: d.xpos[m.body(n).id].copy() for n in names}
    for n in names:  # masses from the manifest
        assert m.body_subtreemass[m.body(n).id] == pytest.approx(manifest.object(n).mass, rel=1e-3)
    for _ in range(int(1.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    for n in names:
        b = m.body(n).id
        drift = np.linalg.norm(d.xpos[b] - p0[n])
        assert drift < 0.005, (n, drift)                      # no sinking, sliding or explosion
        assert abs(d.xmat[b].reshape(3, 3)[2, 2] - 1) < 1e-3    # still upright
        assert np.linalg.norm(d.cvel[b]) < 0.01                  # at rest


def test_unscaled_twin_refused(twin: Path):
    m = Manifest.load(twin)
    m.frame.scaled = False
    m.frame.source = "unscaled"
    with pytest.raises(InputError, match="not metrically scaled"):
        build_spec(m, twin)


def test_missing_parts_named(twin: Path, tmp_path: Path):
    m = Manifest.load(twin)
    m.objects[0].convex_parts = ["objects/nope/part_000.obj"]
    m.objects[0].collision_mesh = None
    with pytest.raises(InputError, match=m.objects[0].name):
        build_spec(m, twin)


def test_table_is_not_doubled_by_background_part_0(tmp_path: Path):
    """Background part 0 is the table box itself (geometry.convert): MJCF added it as a mesh geom beside the
    `table` box, so everything on the table touched it twice (audit 10d G5). URDF, MoveIt, glTF skip it."""
    import warnings

    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.twin.build import build_twin

    g, labels, objects, _ = synthetic_scene(16000, seed=1, obstacle=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        man = build_twin(g, labels, objects, tmp_path, TwinFrame("ground_truth", scaled=True), formats=("mjcf",),
                         progress=False)
    assert len(man.background.convex_parts) >= 2
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "export" / "scene.xml"))
    world_meshes = [m.geom(i).name for i in range(m.ngeom)
                    if m.geom_bodyid[i] == 0 and m.geom_type[i] == mujoco.mjtGeom.mjGEOM_MESH]
    assert world_meshes == [f"background/part_{k}" for k in range(1, len(man.background.convex_parts))]
    d = mujoco.MjData(m)
    for _ in range(200):
        mujoco.mj_step(m, d)
    box = m.body("box").id
    touched = {m.geom(int(c.geom[i])).name for c in d.contact[:d.ncon] for i in (0, 1)
               if m.geom_bodyid[int(c.geom[1 - i])] == box and m.geom_bodyid[int(c.geom[i])] == 0}
    assert touched == {"table"}
