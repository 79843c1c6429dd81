from __future__ import annotations

import numpy as np
import pytest
import torch

from splattwin.splat.appearance import AppearanceModel, fit_affine, heldout_corrected_psnr


def test_starts_at_identity_and_regulariser_is_distance_from_it():
    m = AppearanceModel(3, "affine", reg=0.5)
    img = torch.rand(4, 5, 3)
    torch.testing.assert_close(m.apply(img, 1), img)
    assert float(m.regularizer(1)) == 0.0
    with torch.no_grad():
        m.params[1][:9] = torch.eye(3).flatten() * 0.1  # A = 1.1 I
        m.params[1][9:] = torch.tensor([0.0, 0.2, 0.0])
    torch.testing.assert_close(m.apply(img, 1), 1.1 * img + torch.tensor([0.0, 0.2, 0.0]))
    assert float(m.regularizer(1)) == pytest.approx(0.5 * (3 * 0.01 + 0.04))
    torch.testing.assert_close(m.apply(img, 0), img)  # other views untouched


def test_gain_mode_is_diagonal_and_gradcheck():
    m = AppearanceModel(2, "gain")
    with torch.no_grad():
        m.params[0].copy_(torch.tensor([0.1, -0.2, 0.3, 0.01, 0.02, 0.03]))
    A, b = m.matrix_bias(0)
    torch.testing.assert_close(A, torch.diag(torch.tensor([1.1, 0.8, 1.3])))
    img = torch.rand(3, 4, 3, dtype=torch.float64)

    def f(p):  # the same map, differentiated numerically in float64
        mm = AppearanceModel(1, "affine")
        mm.params[0] = p
        return (mm.apply(img, 0) ** 2).sum() + mm.regularizer(0)

    p = torch.randn(12, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (p,), eps=1e-6, atol=1e-5)


def test_learns_a_known_per_view_colour_shift():
    """Two views of the same 'scene' photographed with different gain/bias: the model recovers each."""
    torch.manual_seed(0)
    scene = torch.rand(16, 16, 3)
    A_true = [torch.diag(torch.tensor([1.2, 1.0, 0.8])), torch.eye(3)]
    b_true = [torch.tensor([0.0, 0.05, 0.1]), torch.zeros(3)]
    photos = [scene @ A.T + b for A, b in zip(A_true, b_true)]
    m = AppearanceModel(2, "affine", lr=1e-2, reg=1e-6)
    for it in range(1500):
        i = it % 2
        loss = ((m.apply(scene, i) - photos[i]) ** 2).mean() + m.regularizer(i)
        loss.backward()
        m.step([i])
    A, b = m.as_arrays()
    np.testing.assert_allclose(A[0], A_true[0].numpy(), atol=0.03)
    np.testing.assert_allclose(b[0], b_true[0].numpy(), atol=0.03)
    np.testing.assert_allclose(A[1], np.eye(3), atol=0.03)


def test_per_view_optimisers_leave_unrendered_views_alone():
    m = AppearanceModel(2, "gain", lr=0.1)
    img = torch.rand(4, 4, 3)
    for _ in range(3):
        (m.apply(img, 0).sum()).backward()
        m.step([0])
    assert m.params[0].abs().sum() > 0 and float(m.params[1].abs().sum()) == 0.0


def test_state_round_trip_through_checkpoint(tmp_path):
    from splattwin.splat import checkpoint as ckpt_io

    m = AppearanceModel(3, "affine", lr=0.05)
    img = torch.rand(4, 4, 3)
    for i in (0, 2, 0):
        m.apply(img, i).mean().backward()
        m.step([i])
    ckpt_io.save(tmp_path / "a.safetensors", {"app": m.state_dict()})
    m2 = AppearanceModel(3, "affine", lr=0.05)
    m2.load_state_dict(ckpt_io.load(tmp_path / "a.safetensors")["app"])
    for a, b in zip(m.params, m2.params):
        torch.testing.assert_close(a, b)
    # the restored Adam moments continue identically
    for mm in (m, m2):
        mm.apply(img, 2).mean().backward()
        mm.step([2])
    torch.testing.assert_close(m.params[2], m2.params[2])
    with pytest.raises(ValueError):
        AppearanceModel(3, "gain").load_state_dict(m.state_dict())
    # the regulariser's centre (the measured start) comes back with it; a broken one is refused
    g = AppearanceModel(2, "gain", init_gains=np.array([[1.2, 1.0, 0.8], [1.0, 1.0, 1.0]]))
    g2 = AppearanceModel(2, "gain")
    g2.load_state_dict(g.state_dict())
    torch.testing.assert_close(g2.prior, g.prior)
    sd = g.state_dict()
    sd["prior"] = torch.full_like(sd["prior"], float("nan"))
    with pytest.raises(ValueError, match="prior"):
        g2.load_state_dict(sd)


def test_fit_affine_recovers_a_colour_transform_and_protocol():
    rng = np.random.default_rng(0)
    render = rng.uniform(0.1, 0.8, (20, 30, 3))
    A = np.array([[1.1, 0.05, 0.0], [0.0, 0.9, 0.02], [0.03, 0.0, 1.05]])
    b = np.array([0.02, -0.01, 0.03])
    gt = render @ A.T + b
    A2, b2 = fit_affine(render, gt, ridge=0.0)
    np.testing.assert_allclose(A2, A, atol=1e-9)
    np.testing.assert_allclose(b2, b, atol=1e-9)
    Ag, bg = fit_affine(render, gt, "gain", ridge=0.0)
    assert np.count_nonzero(Ag - np.diag(np.diag(Ag))) == 0
    r = heldout_corrected_psnr(render.astype(np.float32), np.clip(gt, 0, 1).astype(np.float32))
    assert r["psnr_right_corrected"] > 40 and r["psnr_right_plain"] < 35
    # strong ridge -> the identity
    A3, b3 = fit_affine(render, gt, ridge=1e6)
    np.testing.assert_allclose(A3, np.eye(3), atol=1e-4)


# -- which mode a run gets (appearance.decide / exposure_record) ------------------------------------
from splattwin.splat.appearance import AUTO_MODE, decide, exposure_record  # noqa: E402

VARIES = {"varies": True, "spread_pct": 41.0, "threshold_pct": 10.0, "images_off": ["img_03", "img_07"]}
STEADY = {"varies": False, "spread_pct": 1.2, "threshold_pct": 10.0, "images_off": []}


def test_auto_turns_the_correction_on_only_when_the_exposures_differ(caplog):
    with caplog.at_level("WARNING", logger="splattwin.splat.appearance"):
        rec = decide("auto", VARIES, "poses_report.json")
    assert rec["mode"] == AUTO_MODE == "gain" and rec["decision"] == "auto"
    assert rec["images_off"] == ["img_03", "img_07"] and rec["spread_pct"] == 41.0
    assert "img_03" in caplog.text and "--splat.appearance off" in caplog.text
    steady = decide("auto", STEADY)
    assert steady["mode"] == "off" and steady["decision"] == "none" and steady["spread_pct"] == 1.2
    none = decide("auto", None)
    assert none["mode"] == "off" and none["decision"] == "none" and "not measured" in none["exposure"]
    err = decide("auto", {"error": "no sparse points to compare the images on"})
    assert err["mode"] == "off" and "no sparse points" in err["exposure"]


def test_explicit_modes_are_kept_and_explicit_off_on_differing_photos_warns(caplog):
    with caplog.at_level("WARNING", logger="splattwin.splat.appearance"):
        off = decide("off", VARIES)
    assert off["mode"] == "off" and off["decision"] == "suggested"
    assert "img_07" in caplog.text and "--splat.appearance gain" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="splattwin.splat.appearance"):
        assert decide("off", STEADY)["decision"] == "explicit"
        affine = decide("affine", VARIES)
    assert affine["mode"] == "affine" and affine["decision"] == "explicit"
    assert "appearance" not in caplog.text
    with pytest.raises(ValueError, match="appearance mode"):
        decide("bright", VARIES)


class _Posed:
    def __init__(self, root):
        self.root, self.meta = root, {"path": str(root / "transforms.json")}


def test_exposure_record_reads_the_poses_report_beside_the_dataset(tmp_path, caplog):
    import json

    (tmp_path / "transforms.json").write_text("{}")
    assert exposure_record(_Posed(tmp_path)) == (None, None)          # no report
    rep = tmp_path / "poses_report.json"
    rep.write_text(json.dumps({"method": "known"}))
    assert exposure_record(_Posed(tmp_path)) == (None, rep)           # a report from before the check
    rep.write_text(json.dumps({"exposure": VARIES}))
    assert exposure_record(_Posed(tmp_path)) == (VARIES, rep)
    with caplog.at_level("WARNING", logger="splattwin.splat.appearance"):
        rep.write_text(json.dumps({"exposure": {"varies": "yes", "spread_pct": 3, "images_off": []}}))
        assert exposure_record(_Posed(tmp_path)) == (None, rep)
        rep.write_text("{not json")
        assert exposure_record(_Posed(tmp_path)) == (None, rep)
    assert "malformed \"exposure\"" in caplog.text and "poses_report.json" in caplog.text


# -- where the corrections start (appearance.initial_gains) -------------------------------------------
from splattwin.splat.appearance import initial_gains  # noqa: E402


def test_initial_gains_take_the_measured_rgb_gains():
    rec = {**VARIES, "images": {"img_03": {"gain": 1.2, "rgb_gain": [1.3, 1.2, 1.1], "samples": 90},
                                "img_07": {"gain": 0.8, "rgb_gain": [0.7, 0.8, 0.9], "samples": 80}}}
    g, how = initial_gains(rec, ["img_07", "img_03"])
    np.testing.assert_allclose(g, [[0.7, 0.8, 0.9], [1.3, 1.2, 1.1]])
    assert how == {"init": "measured", "init_views": 2}
    m = AppearanceModel(2, "gain", init_gains=g)
    img = torch.full((2, 2, 3), 0.5)
    torch.testing.assert_close(m.apply(img, 1), img * torch.tensor([1.3, 1.2, 1.1]))   # model -> photo
    assert float(m.regularizer(1).detach()) == 0.0                 # centred on the measurement
    with pytest.raises(ValueError, match="init_gains"):
        AppearanceModel(2, "gain", init_gains=np.ones((3, 3)))


def test_gauge_is_the_corrections_common_gain_and_bias():
    m = AppearanceModel(2, "affine", init_gains=np.array([[1.21, 1.0, 0.5], [1.0, 0.81, 2.0]]))
    assert m.gauge() == {"gain": [1.1, 0.9, 1.0], "gain_start": [1.1, 0.9, 1.0], "bias": [0.0, 0.0, 0.0]}
    with torch.no_grad():
        m.params[0][1] = 0.3                                       # an off-diagonal term: not a level
        m.params[0][-3:] = torch.tensor([0.02, 0.0, -0.01])
        m.params[1][-3:] = torch.tensor([0.0, 0.01, 0.01])
    g = m.gauge()
    np.testing.assert_allclose(g["gain"], [1.1, 0.9, 1.0], atol=1e-4)
    np.testing.assert_allclose(g["bias"], [0.01, 0.005, 0.0], atol=1e-6)
    with torch.no_grad():
        m.params[1][4] = 0.81 * 1.21 - 1.0                          # view 1's green gain x1.21: the mean's x1.1
    assert m.gauge()["gain"][1] == pytest.approx(0.99, abs=1e-4) and m.gauge()["gain_start"] == [1.1, 0.9, 1.0]


@pytest.mark.parametrize("exposure, why", [
    (None, "no exposure check"),
    ({"error": "no sparse points to compare the images on"}, "no sparse points"),
    ({**STEADY}, "no \"images\""),
    ({**STEADY, "images": ["img_03"]}, "no \"images\""),
])
def test_initial_gains_without_a_measurement_start_at_one_and_say_so(exposure, why, caplog):
    with caplog.at_level("INFO", logger="splattwin.splat.appearance"):
        g, how = initial_gains(exposure, ["img_03", "img_07"], "twin/poses/poses_report.json")
    np.testing.assert_array_equal(g, 1.0)
    assert how["init"] == "identity" and how["init_views"] == 0 and why in how["init_why"]
    assert why in caplog.text and "start at gain 1" in caplog.text and "poses_report.json" in caplog.text


def test_initial_gains_skip_malformed_or_missing_entries(caplog):
    bad = {"img_a": {"rgb_gain": "1.2"}, "img_b": {"rgb_gain": [1.1, 1.0]}, "img_c": {"rgb_gain": [0.0, 1, 1]},
           "img_d": {"rgb_gain": [float("nan"), 1, 1]}, "img_e": {"rgb_gain": None}, "img_f": [1.1, 1, 1],
           "img_g": {"rgb_gain": [True, 1, 1]}, "img_h": {"rgb_gain": [1e6, 1, 1]},
           "img_ok": {"rgb_gain": [1.1, 0.9, 1.0]}}
    names = [*bad, "img_missing"]
    with caplog.at_level("INFO", logger="splattwin.splat.appearance"):
        g, how = initial_gains({**VARIES, "images": bad}, names)
    np.testing.assert_allclose(g[names.index("img_ok")], [1.1, 0.9, 1.0])
    others = np.delete(g, names.index("img_ok"), axis=0)
    np.testing.assert_array_equal(others, 1.0)
    assert how["init"] == "measured" and how["init_views"] == 1
    assert "9 of 10 views" in how["init_why"] and "img_a" in caplog.text and "and 3 more" in caplog.text
