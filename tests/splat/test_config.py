from __future__ import annotations

import pytest

from splattwin.splat.config import DEFAULT_EPS2D, LEGACY_EPS2D, TrainConfig, trained_filter


def test_filter_eps2d_is_the_option_or_the_modes_default():
    assert TrainConfig().filter_eps2d() == DEFAULT_EPS2D["classic"] == 0.3
    assert TrainConfig(rasterize_mode="antialiased").filter_eps2d() == DEFAULT_EPS2D["antialiased"] == 0.1
    assert TrainConfig(rasterize_mode="antialiased", eps2d=0.25).filter_eps2d() == 0.25
    assert TrainConfig().to_dict()["eps2d"] == 0.0  # recorded, so the twin is rendered as it was trained


def test_trained_filter_reads_a_recorded_config():
    aa = TrainConfig(rasterize_mode="antialiased").to_dict()
    assert trained_filter(aa) == ("antialiased", 0.1)
    assert trained_filter(TrainConfig(eps2d=0.2).to_dict()) == ("classic", 0.2)
    # before the option existed every config trained with 0.3
    assert trained_filter({"rasterize_mode": "antialiased"}) == ("antialiased", LEGACY_EPS2D) == ("antialiased", 0.3)
    assert trained_filter(None) == trained_filter({}) == ("classic", 0.3)
    for bad in ({"rasterize_mode": "mip"}, {"eps2d": -0.1}, {"eps2d": 1e9}, {"eps2d": "0.1"}, {"eps2d": True},
                {"eps2d": float("nan")}):
        with pytest.raises(ValueError):
            trained_filter(bad)


def test_filter_beside_reads_the_training_record_next_to_a_splat_file(tmp_path):
    import json

    from splattwin.errors import InputError
    from splattwin.splat.config import filter_beside

    ply = tmp_path / "point_cloud.ply"
    assert filter_beside(ply) == ("classic", 0.3)        # no record: a bare PLY
    (tmp_path / "train.json").write_text(json.dumps({"config": TrainConfig(rasterize_mode="antialiased").to_dict()}))
    assert filter_beside(ply) == ("antialiased", 0.1)
    (tmp_path / "train.json").write_text(json.dumps({"config": {"rasterize_mode": "antialiased", "eps2d": 99}}))
    with pytest.raises(InputError, match="eps2d") as e:
        filter_beside(ply)
    assert "train.json" in str(e.value)
    (tmp_path / "train.json").write_text("{not json")
    with pytest.raises(InputError, match="train.json"):
        filter_beside(ply)


def test_filter_for_keeps_the_trained_low_pass_only_in_the_trained_mode():
    from splattwin.splat.config import filter_for

    assert filter_for(("antialiased", 0.1)) == ("antialiased", 0.1)
    assert filter_for(("antialiased", 0.1), "antialiased") == ("antialiased", 0.1)
    assert filter_for(("antialiased", 0.1), "classic") == ("classic", None)   # that mode's own default
