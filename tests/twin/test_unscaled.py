"""An unscaled twin (SfM units) is complete: geometry, every export marked unscaled, viewer layers; only
robot planning refuses it, saying how to give the twin a metric scale (issue #16)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from splattwin.poses.twin_frame import TwinFrame
from splattwin.scene.synthetic import synthetic_scene
from splattwin.splat.gaussians import Gaussians
from splattwin.twin.build import build_twin
from splattwin.twin.manifest import Manifest

S = 7.3  # SfM units per metre


def _build(out: Path, s: float, frame: TwinFrame) -> Manifest:
    g, labels, objects, _ = synthetic_scene(8000, seed=2)
    g = Gaussians(g.means * s, g.quats, g.scales * s, g.opacities, g.sh)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return build_twin(g, labels, objects, out, frame=frame, progress=False)


@pytest.fixture(scope="module")
def unscaled(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("unscaled") / "twin"
    _build(out, S, TwinFrame(source="unscaled", scaled=False, nominal_metre=S))
    return out


@pytest.fixture(scope="module")
def metric(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("metric") / "twin"
    _build(out, 1.0, TwinFrame(source="ground_truth", scaled=True, scale_uncertainty_rel=0.0))
    return out


def test_frame_units_say_unscaled():
    assert TwinFrame().units == "unscaled" and not TwinFrame().scaled
    # an older frame.json of an unscaled twin said "m": loaded, it says what it is
    assert TwinFrame(source="unscaled", scaled=False, units="m").units == "unscaled"
    assert TwinFrame(source="marker", scaled=True).units == "m"
    assert TwinFrame(source="marker", scaled=True, nominal_metre=5.0).length_scale() == 1.0
    assert TwinFrame(nominal_metre=5.0).length_scale() == 5.0
    assert TwinFrame().length_scale(fallback=2.0) == 2.0 and TwinFrame().length_scale() == 1.0


def test_unscaled_twin_has_geometry_like_the_metric_one(unscaled, metric):
    mu, mm = Manifest.load(unscaled), Manifest.load(metric)
    assert mu.frame.units == "unscaled" and not mu.frame.scaled and mu.frame.nominal_metre == S
    raw = json.loads((unscaled / "twin.json").read_text())
    assert raw["frame"]["units"] == "unscaled" and raw["frame"]["scaled"] is False
    assert raw["config"]["geometry"]["dbscan_eps"] == pytest.approx(0.02 * S)  # the thresholds it used
    assert [o.usable for o in mu.objects] == [o.usable for o in mm.objects] == [True] * len(mm.objects)
    for a, b in zip(mu.objects, mm.objects):
        assert np.allclose(a.bbox_extent, np.array(b.bbox_extent) * S, rtol=0.05, atol=0.004 * S), a.name
        assert a.mass == pytest.approx(b.mass, rel=0.05)  # nominal kilograms
        assert (unscaled / a.visual_mesh).is_file() and a.convex_parts
    assert mu.background.table_thickness == pytest.approx(mm.background.table_thickness * S)


def test_every_export_is_written_and_marked(unscaled, metric):
    import mujoco
    import trimesh

    mu = Manifest.load(unscaled)
    assert set(mu.exports) == {"mjcf", "urdf", "moveit", "gltf"}
    ex = unscaled / "export"
    xml = (ex / "scene.xml").read_text()
    assert "UNSCALED" in xml and 'model="splattwin_twin_unscaled"' in xml
    model = mujoco.MjModel.from_xml_path(str(ex / "scene.xml"))  # still a valid model
    assert model.nbody >= 1 + len(mu.objects)
    for f in ["scene.urdf"] + [f"{o.name}.urdf" for o in mu.objects]:
        assert "<!-- UNSCALED twin" in (ex / f).read_text(), f
    for f in ("collision_objects.yaml", "collision_objects_boxes.yaml"):
        assert (ex / "moveit" / f).read_text().startswith("# UNSCALED twin"), f
    assert (ex / "moveit" / "scene.scene").read_text().splitlines()[0] == "splattwin_unscaled"
    glb = trimesh.load(ex / "scene.glb")
    assert glb.metadata["splattwin"]["units"] == "unscaled" and glb.metadata["splattwin"]["scaled"] is False
    # a metric twin's exports carry no such note
    em = metric / "export"
    assert "UNSCALED" not in (em / "scene.xml").read_text() and "UNSCALED" not in (em / "scene.urdf").read_text()
    assert (em / "moveit" / "scene.scene").read_text().splitlines()[0] == "splattwin"
    assert trimesh.load(em / "scene.glb").metadata["splattwin"]["units"] == "m"


def test_viewer_layers_follow_the_nominal_metre(unscaled, metric):
    from splattwin.playback.view_model import TwinView

    vu, vm = TwinView.load(unscaled, meshes=False, robot=False), TwinView.load(metric, meshes=False, robot=False)
    # the same Gaussians in the workspace layer as in the metric twin (margins in nominal metres)
    assert len(vu.splats) == len(vm.splats) > 0 and len(vu.far) == len(vm.far)


def test_plan_refuses_with_how_to_scale(unscaled, capsys):
    from splattwin.cli import main

    assert main(["plan", str(unscaled)]) == 2
    err = capsys.readouterr().err
    assert "not metrically scaled" in err and "--known-length" in err and "--marker-size" in err
    assert "known poses" in err and "depth" in err


def test_render_says_why_an_unscaled_twin_has_no_rollout(unscaled, metric, tmp_path, capsys):
    """`render` told users to run `splattwin plan` first, which refuses every unscaled twin."""
    from splattwin.cli import main

    assert main(["render", str(unscaled), "--out", str(tmp_path / "a.mp4")]) == 2
    err = capsys.readouterr().err
    assert "unscaled" in err and "--known-length" in err and "run `splattwin plan TWIN` first" not in err
    assert main(["render", str(metric), "--out", str(tmp_path / "b.mp4")]) == 2
    assert "run `splattwin plan TWIN` first" in capsys.readouterr().err   # a metric twin: plan it


def test_sweep_refuses_an_unscaled_twin_before_any_work(unscaled, tmp_path, capsys):
    """sweep ran every cell's fusion and geometry on an unscaled twin, then failed each cell (exit 1)."""
    from splattwin.cli import main

    assert main(["sweep", str(unscaled), "--out", str(tmp_path / "sw"), "--kappa", "1.2,1.5", "--trials", "1"]) == 2
    assert "not metrically scaled" in capsys.readouterr().err
    assert not (tmp_path / "sw" / "fusion").exists() and not (tmp_path / "sw" / "twins").exists()


def test_sweep_without_task_on_another_twin_asks_for_one(metric, tmp_path, capsys):
    """Without --task sweep named the package's own default.yaml and its 'target_frame' region."""
    from splattwin.cli import main

    assert main(["sweep", str(metric), "--out", str(tmp_path / "sw"), "--sigma", "0.003", "--trials", "1"]) == 2
    err = capsys.readouterr().err
    assert "no --task given" in err and "--task TASK.yaml" in err and "twin.json" in err
