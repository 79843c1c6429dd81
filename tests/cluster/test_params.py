"""Sweep parameters map onto the stages' options objects by field name, parsed by the field's type."""

from __future__ import annotations

import pytest

from splattwin.cluster import params as P
from splattwin.errors import InputError
from splattwin.geometry.options import GeometryOptions
from splattwin.robot.options import RobotOptions
from splattwin.semantics.options import FusionOptions


def test_aliases_and_targets():
    assert P.canonical("kappa") == "fusion.kappa"
    assert P.canonical("fusion-iters") == "fusion.iters"
    assert P.canonical("sigma") == "trials.sigma"
    assert P.canonical("geometry.min_opacity") == "geometry.min_opacity"
    assert P.canonical("fusion.depth_tol") == "fusion.depth_tol"


@pytest.mark.parametrize("bad", ["foo", "fusion.nope", "geometry.alpha_factors", "trials.seed", "trials.twin_dir",
                                 "robot.sigma", "fusion."])
def test_unknown_parameters_are_input_errors(bad):
    with pytest.raises(InputError):
        P.canonical(bad)


def test_values_parsed_by_field_type():
    assert P.parse_values("fusion.kappa", "1.2, 2") == [1.2, 2.0]
    assert P.parse_values("fusion.iters", "1,3") == [1, 3]
    assert all(type(v) is int for v in P.parse_values("geometry.dbscan_min_samples", "5,10"))
    assert P.parse_values("geometry.use_alpha", "true,off") == [True, False]
    assert P.parse_values("geometry.max_scale", "none,0.01") == [None, 0.01]
    assert P.parse_values("trials.in_hand", "sensed,planned") == ["sensed", "planned"]
    assert P.parse_assignment("geometry.min_opacity=0.05,0.1") == ("geometry.min_opacity", [0.05, 0.1])
    for name, text in [("fusion.iters", "1.5"), ("fusion.kappa", "abc"), ("fusion.kappa", "nan"),
                       ("geometry.use_alpha", "maybe"), ("trials.sigma", "0.2"), ("fusion.kappa", "0"),
                       ("fusion.kappa", "1,1"), ("trials.in_hand", "guessed"),
                       ("trials.planner", "RRTconnect")]:   # choices are checked (a planner typo ran every task)
        with pytest.raises(InputError):
            P.parse_values(name, text)
    with pytest.raises(InputError, match="NAME=V1,V2"):
        P.parse_assignment("geometry.min_opacity")


@pytest.mark.parametrize("name,text", [("geometry.min_opacity", "-1"), ("geometry.min_opacity", "2"),
                                       ("geometry.dbscan_eps", "-0.01"), ("geometry.dbscan_eps", "0"),
                                       ("geometry.dbscan_min_samples", "0"), ("geometry.foot_height", "-0.001"),
                                       ("fusion.depth_tol", "-0.01"), ("fusion.knn_threshold", "1.5"),
                                       ("geometry.max_scale", "-0.1")])
def test_values_outside_the_fields_domain_are_refused_naming_the_parameter(name, text):
    """Before, these passed the grammar: min_opacity=-1 ran every cell (exit 0), dbscan_eps=-0.01 failed inside
    every geometry task with scikit-learn's error (exit 1)."""
    with pytest.raises(InputError, match=rf"sweep parameter {name} must be"):
        P.parse_values(name, f"0.5,{text}" if name.endswith(("opacity", "threshold")) else text)


def test_values_inside_the_fields_domain_pass():
    assert P.parse_values("geometry.dbscan_voxel", "0,0.005") == [0.0, 0.005]   # 0: documented as off
    assert P.parse_values("geometry.foot_height", "0") == [0.0]
    assert P.parse_values("geometry.max_scale", "none,0.02") == [None, 0.02]
    assert P.parse_values("geometry.min_opacity", "0,1") == [0.0, 1.0]


def test_sweep_cli_exits_2_on_a_value_outside_the_domain(tmp_path, capsys):
    from splattwin.cli import main

    assert main(["sweep", str(tmp_path), "--out", str(tmp_path / "o"), "--clean", "min_opacity=-1"]) == 2
    assert "geometry.min_opacity must be in [0, 1], got -1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_split_and_apply_set_the_named_fields():
    parts = P.split({"fusion.kappa": 1.2, "geometry.min_opacity": 0.05, "trials.sigma": 0.004, "fusion.iters": 1})
    assert parts == {"fusion": {"kappa": 1.2, "iters": 1}, "geometry": {"min_opacity": 0.05}, "trials": {"sigma": 0.004}}
    f = P.apply(FusionOptions(), parts["fusion"])
    assert (f.kappa, f.iters, f.depth_tol) == (1.2, 1, FusionOptions().depth_tol)
    g = P.apply(GeometryOptions(), parts["geometry"])
    assert g.min_opacity == 0.05 and g.dbscan_eps == GeometryOptions().dbscan_eps
    t = P.apply(RobotOptions(), parts["trials"])
    assert t.sigma == 0.004 and t.seed == RobotOptions().seed
    assert P.default("fusion.kappa") == FusionOptions().kappa


def test_cell_trials_counts_a_yaw_only_cell_in_full():
    """The trials a sweep cell runs (its jobs and the progress bar's total both count with `cell_trials`): one
    when nothing is perturbed, all of them when only the yaw is (the total counted one for any sigma 0, so
    `--param trials.sigma=0 --param trials.sigma_yaw=0.05` showed a bar that ended short of its work)."""
    from pathlib import Path

    from splattwin.cluster.sweep import SweepSpec, cell_trials
    from splattwin.robot.trials import TrialSpec

    spec = SweepSpec(twin=Path("twin"), grid={}, trial=TrialSpec(twin_dir="twin", task_path=None), trials=7)
    assert cell_trials({"trial_params": {"sigma": 0.0}}, spec) == 1
    assert cell_trials({"trial_params": {"sigma": 0.0, "sigma_yaw": 0.0}}, spec) == 1
    assert cell_trials({"trial_params": {"sigma": 0.0, "sigma_yaw": 0.05}}, spec) == 7
    assert cell_trials({"trial_params": {"sigma": 0.01}}, spec) == 7
    yaw_spec = SweepSpec(twin=Path("twin"), grid={}, trials=3,
                         trial=TrialSpec(twin_dir="twin", task_path=None, sigma=0.0, sigma_yaw=0.1))
    assert cell_trials({"trial_params": {}}, yaw_spec) == 3
