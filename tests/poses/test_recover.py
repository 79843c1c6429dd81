"""Re-registering images the registration sanity check dropped (colmap_worker's recover step, run by
`splattwin.poses.sfm` once the dropped images are all the best model lacks, or after the attempts): an
image removed from the embedded scene's SfM model comes back by absolute pose at its old place; a wrong
registration (a parallax-free copy of another camera, a frame out of the walking order) is refused; known
intrinsics stay fixed."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.capture.camera import Camera
from splattwin.poses.sfm import SfmOptions, frame_order


def _model_centres(rec) -> dict[str, np.ndarray]:
    return {rec.image(i).name: np.asarray(rec.image(i).projection_center()) for i in rec.reg_image_ids()}


def _job(sfm_dir, base, out, names, **kw) -> dict:
    import json

    from splattwin.poses.sfm import mapping_options

    n = len(json.loads((sfm_dir / "sfm_config.json").read_text())["images"])
    return {"db": str(sfm_dir / "database.db"), "image_root": kw.pop("image_root"), "base": str(base),
            "out": str(out), "names": names, "min_observations": 30, "seed": 0,
            "options": mapping_options(SfmOptions(), n, "relaxed", 1), **kw}


@pytest.fixture(scope="module")
def dropped_model(default_unscaled, sfm_default_dir, tmp_path_factory):
    """(full model, model without one image, that image's name) from the embedded scene's SfM."""
    import pycolmap

    from splattwin.poses.colmap_worker import step_drop

    full = pycolmap.Reconstruction(str(sfm_default_dir / "sparse"))
    names = sorted(full.image(i).name for i in full.reg_image_ids())
    gone = names[len(names) // 2]
    out = tmp_path_factory.mktemp("recover") / "dropped"
    step_drop({"base": str(sfm_default_dir / "sparse"), "out": str(out), "names": [gone]})
    return full, out, gone


def test_dropped_image_comes_back_at_its_place(dropped_model, sfm_default_dir, scene_default, tmp_path):
    import pycolmap

    from splattwin.poses.colmap_worker import step_recover

    full, base, gone = dropped_model
    before = pycolmap.Reconstruction(str(base))
    assert gone not in {before.image(i).name for i in before.reg_image_ids()}
    res = step_recover(_job(sfm_default_dir, base, tmp_path / "rec", [gone], image_root=str(scene_default / "images")))
    assert set(res["recovered"]) == {gone} and res["rejected"] == {}
    assert res["recovered"][gone]["method"] == "absolute" and res["recovered"][gone]["observations"] >= 30
    rec = pycolmap.Reconstruction(res["path"])
    assert rec.num_reg_images() == full.num_reg_images()
    # the same frame as the full model up to the bundle adjustment's small moves: compare after a Sim(3)
    c0, c1 = _model_centres(full), _model_centres(rec)
    common = sorted(c0)
    src = np.array([c1[n] for n in common])
    tgt = np.array([c0[n] for n in common])
    sim = pycolmap.estimate_sim3d(src, tgt)
    aligned = src @ sim.matrix()[:, :3].T + sim.matrix()[:, 3]
    spread = np.ptp(tgt, axis=0).max()
    k = common.index(gone)
    assert np.linalg.norm(aligned[k] - tgt[k]) < 0.01 * spread
    assert rec.compute_mean_reprojection_error() < 1.0


def test_nothing_to_recover_writes_nothing(dropped_model, sfm_default_dir, scene_default, tmp_path):
    """An image with no features matched to the model (a name the database lacks) is reported, not added."""
    from splattwin.poses.colmap_worker import step_recover

    _, base, _ = dropped_model
    res = step_recover(_job(sfm_default_dir, base, tmp_path / "rec", ["nope.png"],
                            image_root=str(scene_default / "images")))
    assert res["recovered"] == {} and "nope.png" in res["rejected"] and "path" not in res
    assert not (tmp_path / "rec").exists()


def test_recovery_refuses_when_it_cannot_pass_the_check(dropped_model, sfm_default_dir, scene_default, tmp_path):
    """The same image, but demanding more observations than it can have: refused with the reason."""
    from splattwin.poses.colmap_worker import step_recover

    _, base, gone = dropped_model
    job = _job(sfm_default_dir, base, tmp_path / "rec", [gone], image_root=str(scene_default / "images"))
    job["min_observations"] = 100000
    res = step_recover(job)
    assert res["recovered"] == {} and "need >= 100000" in res["rejected"][gone]


# -- the guards, on synthetic cameras -------------------------------------------------------------------
def _look_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    c, t = np.asarray(centre, float), np.asarray(target, float)
    z = (t - c) / np.linalg.norm(t - c)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = c
    return T


def _walk(n: int = 8, step_deg: float = 30.0):
    """n cameras walking around a table (z = 0) at height 3, radius 4, azimuth step `step_deg`; points on
    the table. Names frame000..frame(n-1) in walking order."""
    K = np.array([[460.0, 0, 341.5], [0, 460.0, 192.0], [0, 0, 1]])
    cams = {}
    for i in range(n):
        a = np.radians(step_deg * i)
        cams[f"frame{i:03d}.jpg"] = Camera(K=K, width=683, height=384, name=f"frame{i:03d}.jpg",
                                           T_world_cam=_look_at([4 * np.cos(a), 4 * np.sin(a), 3.0], [0, 0, 0]))
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, (500, 2)), 0.002 * rng.standard_normal(500)])
    return cams, pts


def test_out_of_order_frame_is_refused_and_in_order_kept():
    from splattwin.poses.colmap_worker import _out_of_order

    cams, pts = _walk()
    order = sorted(cams)
    assert _out_of_order(cams, pts, "frame003.jpg", order, 10.0, 0) == ""
    # frame003 placed where frame006 stands (the way a wrong registration lands it across the scene)
    T = cams["frame006.jpg"].T_world_cam.copy()
    T[:3, 3] += np.array([0.3, 0.0, 0.0])
    cams["frame003.jpg"] = Camera(K=cams["frame003.jpg"].K, width=683, height=384, T_world_cam=T, name="frame003.jpg")
    why = _out_of_order(cams, pts, "frame003.jpg", order, 10.0, 0)
    assert "out of the capture order" in why and "frame002.jpg" in why
    # no order known (not numbered frames): nothing to check
    assert _out_of_order(cams, pts, "frame003.jpg", [], 10.0, 0) == ""


def test_parallax_free_copy_of_a_camera_is_refused():
    from splattwin.poses.colmap_worker import _coincident

    cams, _ = _walk()
    assert _coincident(cams, "frame004.jpg", 0.05, 10.0) == ""
    c = cams["frame005.jpg"].center
    cams["frame004.jpg"] = Camera(K=cams["frame004.jpg"].K, width=683, height=384, name="frame004.jpg",
                                  T_world_cam=_look_at(c, [1.0, 1.5, 0.0]))  # same centre, turned
    why = _coincident(cams, "frame004.jpg", 0.05, 10.0)
    assert "frame005.jpg" in why and "parallax-free" in why


def test_frame_order_of_numbered_frames():
    names = ["frame000112.jpg", "frame000020.jpg", "frame000069.jpg"]
    assert frame_order(names, SfmOptions()) == ["frame000020.jpg", "frame000069.jpg", "frame000112.jpg"]
    assert frame_order(["b10.png", "a9.png"], SfmOptions()) == ["a9.png", "b10.png"]
    assert frame_order(["statue.jpg", "img2.jpg"], SfmOptions()) == []  # not all numbered
    assert frame_order(names, SfmOptions(ordered=False)) == []


def test_sfm_recovers_a_dropped_image_and_reports_it(dropped_model, sfm_default_dir, scene_default, tmp_path):
    """The SfM side (`sfm._recovered`): an image the check dropped in some attempt and the best model
    lacks is re-registered in the worker, the model re-checked, and the result logged as the "recover"
    attempt (attempts.json -> poses_report.json) and in the check's "recovered"."""
    import json
    import shutil

    import pycolmap

    from splattwin.poses.progress import StageProgress
    from splattwin.poses.sfm import Attempt, _outcome, _recovered, SfmRun

    _, base, gone = dropped_model
    work = tmp_path / "work"
    work.mkdir()
    shutil.copyfile(sfm_default_dir / "database.db", work / "database.db")
    names = json.loads((sfm_default_dir / "sfm_config.json").read_text())["images"]
    with StageProgress(False) as bar:
        run = SfmRun(work, scene_default / "images", names, SfmOptions(), bar)
        run.dropped = {gone: "posed below the table (test)"}
        best = _outcome([pycolmap.Reconstruction(str(base))], [base], work / "database.db")
        n0 = best.registered
        out, attempt = _recovered(run, best, Attempt("default", "default settings"), [], work / "attempts.json")
    assert out.registered == n0 + 1 and attempt.name == "default+recovered"
    assert gone in {out.rec.image(i).name for i in out.rec.reg_image_ids()}
    assert out.check["recovered"][gone]["method"] == "absolute" and out.check["dropped"] == {}
    log = json.loads((work / "attempts.json").read_text())
    assert log[-1]["name"] == "recover" and gone in log[-1]["recovered"] and log[-1]["registered"] == n0 + 1
    assert gone not in run.dropped and (work / "models" / "recovered").is_dir()
    # a second recovery (against a later, better model) has its own model folder and log entry
    with StageProgress(False) as bar:
        run = SfmRun(work, scene_default / "images", names, SfmOptions(), bar)
        run.dropped = {gone: "test"}
        again, attempt = _recovered(run, best, Attempt("guided", "x"), log, work / "attempts.json",
                                    tag="recover_final")
    assert again.registered == n0 + 1 and attempt.name == "guided+recovered"
    assert (work / "models" / "recovered_recover_final").is_dir()
    log = json.loads((work / "attempts.json").read_text())
    assert [e["name"] for e in log] == ["recover", "recover_final"]
    # recovery off: the model stays as it is
    with StageProgress(False) as bar:
        run = SfmRun(work, scene_default / "images", names, SfmOptions(recover_dropped=False), bar)
        run.dropped = {gone: "test"}
        same, _ = _recovered(run, best, Attempt("default", "x"), [], work / "attempts2.json")
    assert same is best


def test_plane_homography_candidate_lands_near_the_true_pose(dropped_model, sfm_default_dir, scene_default):
    """The table-plane homography candidate (what re-registered the cake's frame000096, where absolute
    pose found nothing): on the embedded tabletop, the dropped image's candidate from its best-matched
    registered image is close to where the full model has it (same frame: the drop step keeps it)."""
    import pycolmap

    from splattwin.poses.colmap_worker import _plane_homography_candidates

    full, base, gone = dropped_model
    model = pycolmap.Reconstruction(str(base))
    db = str(sfm_default_dir / "database.db")
    with pycolmap.Database.open(db) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
    tried: list = []
    job = _job(sfm_default_dir, base, "unused", [gone], image_root=str(scene_default / "images"))
    cands = list(_plane_homography_candidates(model, db, ids, gone, tried, job))
    assert cands, tried
    method, T = cands[0]
    assert method.startswith("plane_homography via ")
    true = next(full.image(i) for i in full.reg_image_ids() if full.image(i).name == gone)
    c_true = np.asarray(true.projection_center())
    c = -T[:, :3].T @ T[:, 3]
    spread = np.ptp(np.array(list(_model_centres(full).values())), axis=0).max()
    assert np.linalg.norm(c - c_true) < 0.05 * spread
    R_err = T[:, :3] @ true.cam_from_world().rotation.matrix().T
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 3.0


def test_drop_and_recover_keep_known_intrinsics(dropped_model, sfm_default_dir, scene_default, tmp_path):
    """With known intrinsics (mapping options ba_refine_* False) the drop's and the recovery's bundle
    adjustments move poses and points only; by default they refine the focal length as the mapper does."""
    import pycolmap

    from splattwin.poses.colmap_worker import step_drop, step_recover
    from splattwin.poses.sfm import mapping_options

    full, _, gone = dropped_model
    n = full.num_reg_images()
    fixed = mapping_options(SfmOptions(intrinsics=(1.0, 1.0, 0.0, 0.0)), n, "relaxed", 1)
    # cameras pulled 3 % off the model's focal length: a refining BA moves them back, a fixed one must not
    base = tmp_path / "base"
    rec = pycolmap.Reconstruction(str(sfm_default_dir / "sparse"))
    for cam in rec.cameras.values():
        p = np.array(cam.params)
        p[0] *= 1.03
        cam.params = p
    base.mkdir()
    rec.write(str(base))
    given = {c: np.array(cam.params) for c, cam in rec.cameras.items()}

    def params(path) -> dict:
        return {c: np.array(cam.params) for c, cam in pycolmap.Reconstruction(str(path)).cameras.items()}

    step_drop({"base": str(base), "out": str(tmp_path / "d_fixed"), "names": [gone], "options": fixed})
    step_drop({"base": str(base), "out": str(tmp_path / "d_free"), "names": [gone]})
    kept, free = params(tmp_path / "d_fixed"), params(tmp_path / "d_free")
    assert all(np.array_equal(kept[c], given[c]) for c in kept)
    assert any(abs(free[c][0] / given[c][0] - 1) > 1e-3 for c in free)  # the default refines the focal
    res = step_recover({**_job(sfm_default_dir, tmp_path / "d_fixed", tmp_path / "rec", [gone],
                               image_root=str(scene_default / "images")), "options": fixed})
    assert set(res["recovered"]) == {gone}
    after = params(res["path"])
    assert all(np.array_equal(after[c], given[c]) for c in after if c in given)
