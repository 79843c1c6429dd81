"""Child-process side of `splattwin.poses.colmap_process`: runs one pycolmap step and reports progress.

pycolmap's calls block in C++ for seconds to minutes and do not return to Python on Ctrl-C, so each heavy
step (feature extraction, matching, mapping, triangulation, sub-model merging) runs in this separate
process, which the parent can terminate at once. Protocol: the parent starts
`python -m splattwin.poses.colmap_worker JOB.json`; this process writes one JSON object per line to stdout
(`{"event": "progress", ...}`, then `{"event": "result", ...}` or `{"event": "error", "message": ...}`).
Everything it writes besides the COLMAP database (which is SQLite: transactional, a killed writer leaves
the last committed state) goes to a temporary folder that is renamed into place when complete.

Options arrive as `{"dotted.attribute.path": value}` dicts and are set on the pycolmap option objects, so
the parent decides every setting and this file holds no tuning.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable


def _write_model(rec, out: Path) -> None:
    """Write a pycolmap Reconstruction to the folder `out` atomically (a sibling temp folder, renamed)."""
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rec.write(str(tmp))
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)


def emit(event: str, **kw: Any) -> None:
    """One protocol line to the parent."""
    sys.stdout.write(json.dumps({"event": event, **kw}) + "\n")
    sys.stdout.flush()


def _set_options(obj: Any, values: dict[str, Any]) -> Any:
    """Set dotted attributes (`"mapper.init_min_num_inliers": 15`) on a pycolmap options object."""
    for key, value in values.items():
        target = obj
        *path, last = key.split(".")
        for part in path:
            target = getattr(target, part)
        if not hasattr(target, last):
            raise AttributeError(f"{type(target).__name__} has no option {last!r} ({key})")
        setattr(target, last, value)
    return obj


def _ensure_db(db: str) -> None:
    import pycolmap

    pycolmap.Database.open(db).close()  # creates the schema if the file is new


# -- steps --------------------------------------------------------------------------------------------
def step_extract(job: dict) -> dict:
    """Import the images camera group by camera group (one COLMAP camera per group, ids in a fixed order),
    then extract SIFT features of all of them in one multi-threaded call."""
    import pycolmap

    db, root = job["db"], job["image_root"]
    _ensure_db(db)
    with pycolmap.Database.open(db) as d:
        have = {im.name for im in d.read_all_images()}
    for g in job["groups"]:
        new = [n for n in g["names"] if n not in have]
        if not new:
            continue
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = g["camera_model"]
        if g.get("camera_params"):
            reader.camera_params = g["camera_params"]
        mode = pycolmap.CameraMode.PER_IMAGE if g.get("per_image") else pycolmap.CameraMode.SINGLE
        pycolmap.import_images(db, root, camera_mode=mode, image_names=new, options=reader)
        if g.get("prior_focal") is not None:
            with pycolmap.Database.open(db) as d:
                ids = {d.read_image_with_name(n).camera_id for n in new}
                for cid in ids:
                    cam = d.read_camera(cid)
                    cam.has_prior_focal_length = bool(g["prior_focal"])
                    d.update_camera(cam)
    ext = _set_options(pycolmap.FeatureExtractionOptions(), job["extraction"])
    reader = pycolmap.ImageReaderOptions()
    if job.get("mask_root"):   # <mask_root>/<image name>.png: no features where it is 0 (transparent pixels)
        reader.mask_path = job["mask_root"]
    pycolmap.extract_features(db, root, image_names=job["names"], reader_options=reader, extraction_options=ext,
                              device=pycolmap.Device.cpu)
    with pycolmap.Database.open(db) as d:
        counts = {im.name: int(d.num_keypoints_for_image(im.image_id)) for im in d.read_all_images()}
    return {"keypoints": counts}


def step_match(job: dict) -> dict:
    """Match and verify image pairs: exhaustive, sequential (+ loop closure), vocabulary-tree retrieval (both
    with a visual index built from this capture's own descriptors), or an explicit pair list."""
    import pycolmap

    db = job["db"]
    mopts = _set_options(pycolmap.FeatureMatchingOptions(), job["matching"])
    vopts = _set_options(pycolmap.TwoViewGeometryOptions(), job["verification"])
    kind = job["kind"]
    cpu = pycolmap.Device.cpu
    if kind == "exhaustive":
        popts = _set_options(pycolmap.ExhaustivePairingOptions(), job.get("pairing", {}))
        pycolmap.match_exhaustive(db, matching_options=mopts, pairing_options=popts, verification_options=vopts,
                                  device=cpu)
    elif kind == "sequential":
        popts = _set_options(pycolmap.SequentialPairingOptions(), job.get("pairing", {}))
        if job.get("loop_closure"):
            popts.loop_detection = True
            popts.vocab_tree_path = _build_visual_index(db, job["loop_closure"])
        pycolmap.match_sequential(db, matching_options=mopts, pairing_options=popts, verification_options=vopts,
                                  device=cpu)
    elif kind == "vocabtree":
        popts = _set_options(pycolmap.VocabTreePairingOptions(), job.get("pairing", {}))
        popts.vocab_tree_path = _build_visual_index(db, job["loop_closure"])
        pycolmap.match_vocabtree(db, matching_options=mopts, pairing_options=popts, verification_options=vopts,
                                 device=cpu)
    elif kind == "pairs":
        popts = _set_options(pycolmap.ImportedPairingOptions(), job.get("pairing", {}))
        popts.match_list_path = job["pairs_file"]
        pycolmap.match_image_pairs(db, matching_options=mopts, pairing_options=popts, verification_options=vopts,
                                   device=cpu)
    else:
        raise ValueError(f"unknown matcher kind {kind!r}")
    with pycolmap.Database.open(db) as d:
        return {"verified_pairs": int(d.num_verified_image_pairs())}


def _build_visual_index(db: str, spec: dict) -> str:
    """A small visual vocabulary (k-means tree) from a sample of the capture's own SIFT descriptors, written
    to spec["path"]: loop detection needs one and COLMAP's pre-trained trees are a download we avoid."""
    import numpy as np
    import pycolmap

    path = spec["path"]
    if Path(path).is_file():
        return path
    rng = np.random.default_rng(0)
    per_image = int(spec.get("descriptors_per_image", 500))
    sample = []
    with pycolmap.Database.open(db) as d:
        for im in d.read_all_images():
            desc = d.read_descriptors(im.image_id).data
            if len(desc) > per_image:
                desc = desc[np.sort(rng.choice(len(desc), per_image, replace=False))]
            sample.append(np.asarray(desc, dtype=np.float32))
    data = np.concatenate(sample) if sample else np.zeros((0, 128), np.float32)
    words = int(min(spec.get("num_visual_words", 4096), max(64, len(data) // 40)))
    index = pycolmap.VisualIndex.create(128, 64)
    bo = pycolmap.VisualIndex.BuildOptions()
    bo.num_visual_words = words
    bo.num_iterations = int(spec.get("num_iterations", 25))
    bo.num_rounds = 1
    bo.num_threads = int(spec.get("num_threads", -1))
    index.build(bo, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, data))
    tmp = path + ".tmp"
    index.write(tmp)
    os.replace(tmp, path)
    return path


def step_map(job: dict) -> dict:
    """Incremental mapping into job["out"]/<i> (sub-models, largest first; written to a temp folder, then
    renamed). With several `seeds` the mapping is repeated with each random seed (cheap for small sets,
    and on weakly connected captures the registration order changes what registers) and the run whose
    largest model registers the most images is kept; it stops early once all images register."""
    import pycolmap

    out = Path(job["out"])
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    n = int(job.get("num_images", 0))
    seeds = job.get("seeds") or [None]
    best: dict | None = None
    best_reg, best_seed = -1, None
    for k, seed in enumerate(seeds):
        opts = _set_options(pycolmap.IncrementalPipelineOptions(), job["options"])
        if seed is not None:
            opts.random_seed = int(seed)
            opts.mapper.random_seed = int(seed)
        done = [0]

        def _next() -> None:
            done[0] += 1
            emit("progress", done=min(done[0] + 1, n), total=n, run=k + 1, runs=len(seeds))

        run_dir = tmp / f"run{k}"
        run_dir.mkdir()
        recs = pycolmap.incremental_mapping(job["db"], job["image_root"], str(run_dir), options=opts,
                                            initial_image_pair_callback=_next, next_image_callback=_next)
        shutil.rmtree(run_dir)
        reg = max((r.num_reg_images() for r in recs.values()), default=0)
        if reg > best_reg:
            best, best_reg, best_seed = recs, reg, seed
        if best_reg >= n:
            break
    models = []
    for i, (_, rec) in enumerate(sorted((best or {}).items(), key=lambda kv: -kv[1].num_reg_images())):
        d = tmp / str(i)
        d.mkdir()
        rec.write(str(d))
        models.append({"path": str(out / str(i)), "registered": int(rec.num_reg_images())})
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)
    return {"models": models, "seed": best_seed}


def _reconstruction_from_db(db: str):
    """An empty Reconstruction holding the database's cameras, rigs, frames and images (same ids)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(db) as d:
        for cam in d.read_all_cameras():
            rec.add_camera(cam)
        for rig in d.read_all_rigs():
            rec.add_rig(rig)
        for fr in d.read_all_frames():
            rec.add_frame(fr)
        for im in d.read_all_images():
            rec.add_image(im)
    return rec


def _set_pose(rec, image_id: int, T_cam_world) -> None:
    import numpy as np
    import pycolmap

    T = np.asarray(T_cam_world, dtype=np.float64)
    im = rec.image(image_id)
    frame = rec.frame(im.frame_id)
    frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
    rec.register_frame(im.frame_id)


def _triangulation_options(values: dict):
    import pycolmap

    return _set_options(pycolmap.IncrementalPipelineOptions(), values)


def step_triangulate(job: dict) -> dict:
    """Points from known poses: the database's features and matches triangulated with every camera pose
    (and the intrinsics) held fixed: COLMAP's point triangulator."""
    import pycolmap

    db, root, out = job["db"], job["image_root"], Path(job["out"])
    rec = _reconstruction_from_db(db)
    poses = job["poses"]  # name -> 3x4 cam_from_world
    with pycolmap.Database.open(db) as d:
        for im in d.read_all_images():
            if im.name in poses:
                _set_pose(rec, im.image_id, poses[im.name])
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    res = pycolmap.triangulate_points(rec, db, root, str(tmp), clear_points=True,
                                      options=_triangulation_options(job.get("options", {})),
                                      refine_intrinsics=False)
    res.write(str(tmp))
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)
    return {"points": int(res.num_points3D()), "registered": int(res.num_reg_images())}


def step_merge(job: dict) -> dict:
    """Complete the base model with images other models registered (sub-models of the same mapping, or
    models of other attempts on other databases): each donor is aligned to the base by a Sim(3) of the
    camera centres of >= `min_common_images` shared images, the images the base lacks get the aligned
    poses, then all points are re-triangulated from the base's database and everything is bundle-adjusted.
    An added image is kept only if it then observes >= `min_observations` points with a mean reprojection
    error <= `max_error_px` (default 10 and 2 px: the relaxed mapper itself registers images
    that observe ~10 points on the weakly textured cake photos); otherwise it is dropped and the merge
    redone without it."""
    import numpy as np
    import pycolmap

    db, root, out = job["db"], job["image_root"], Path(job["out"])
    base = pycolmap.Reconstruction(job["base"])
    donors = [pycolmap.Reconstruction(p) for p in job["donors"]]
    min_common = int(job.get("min_common_images", 3))
    base_names = {base.image(i).name: base.image(i).cam_from_world().matrix() for i in base.reg_image_ids()}
    added: dict[str, np.ndarray] = {}
    for donor in donors:
        reg = {donor.image(i).name: i for i in donor.reg_image_ids()}
        new = [n for n in reg if n not in base_names and n not in added]
        common = [n for n in reg if n in base_names]
        if not new or len(common) < min_common:
            continue
        src = np.array([donor.image(reg[n]).projection_center() for n in common])
        tgt = np.array([-base_names[n][:, :3].T @ base_names[n][:, 3] for n in common])
        spread = float(np.linalg.norm(tgt - tgt.mean(0), axis=1).max()) or 1.0
        # robust: a shared camera one model placed wrongly must not drag the alignment
        ransac = pycolmap.RANSACOptions()
        ransac.max_error = 0.05 * spread
        ransac.random_seed = 0
        fit = pycolmap.estimate_sim3d_robust(src, tgt, ransac)
        if not fit or fit.get("tgt_from_src") is None or int(fit["num_inliers"]) < min_common:
            continue  # the shared cameras disagree: the models differ too much to combine
        donor.transform(fit["tgt_from_src"])
        for n in new:
            added[n] = donor.image(reg[n]).cam_from_world().matrix()
    if not added:
        return {"merged": False, "registered": int(base.num_reg_images())}
    kept = dict(added)
    rec = None
    for _ in range(len(added) + 1):
        rec = _merged(db, root, base, kept, job)
        bad = [n for n in kept if not _image_ok(rec, n, int(job.get("min_observations", 10)),
                                                float(job.get("max_error_px", 2.0)))]
        if not bad:
            break
        for n in bad:
            kept.pop(n)
        if not kept:
            return {"merged": False, "registered": int(base.num_reg_images()), "rejected": sorted(added)}
    _write_model(rec, out)
    return {"merged": True, "registered": int(rec.num_reg_images()), "path": str(out), "added": sorted(kept),
            "rejected": sorted(set(added) - set(kept))}


def _merged(db: str, root: str, base, added: dict, job: dict):
    """Base poses + added poses in a reconstruction of `db`, points triangulated, then bundle-adjusted."""
    import pycolmap

    full = _reconstruction_from_db(db)
    by_name = {full.image(i).name: i for i in full.images}
    for i in base.reg_image_ids():
        n = base.image(i).name
        _set_pose(full, by_name[n], base.image(i).cam_from_world().matrix())
    for n, T in added.items():
        _set_pose(full, by_name[n], T)
    base_cams = {base.image(i).name: base.camera(base.image(i).camera_id) for i in base.reg_image_ids()}
    for n, cam in base_cams.items():  # the base model's refined intrinsics
        full.cameras[full.image(by_name[n]).camera_id].params = cam.params
    with tempfile.TemporaryDirectory() as scratch:
        rec = pycolmap.triangulate_points(full, db, root, scratch, clear_points=True,
                                          options=_triangulation_options(job.get("options", {})),
                                          refine_intrinsics=False)
    _bundle_adjust(rec, job.get("options", {}))
    return rec


def _bundle_adjust(rec, options: dict) -> None:
    """Global bundle adjustment of `rec` in place, refining the intrinsics only as the mapping options
    (`sfm.mapping_options`) let the mapper: known intrinsics stay as given (pycolmap's
    BundleAdjustmentOptions refine the focal length and distortion by default)."""
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.print_summary = False
    ba.refine_focal_length = bool(options.get("ba_refine_focal_length", True))
    ba.refine_principal_point = bool(options.get("ba_refine_principal_point", False))
    ba.refine_extra_params = bool(options.get("ba_refine_extra_params", True))
    pycolmap.bundle_adjustment(rec, ba)


def _image_ok(rec, name: str, min_obs: int, max_err: float) -> bool:
    import numpy as np

    im = next(rec.image(i) for i in rec.reg_image_ids() if rec.image(i).name == name)
    errs = []
    for p2 in im.points2D:
        if p2.has_point3D():
            uv = im.project_point(rec.points3D[p2.point3D_id].xyz)
            if uv is not None:
                errs.append(float(np.linalg.norm(np.asarray(uv).ravel() - np.asarray(p2.xy).ravel())))
    return len(errs) >= min_obs and float(np.mean(errs)) <= max_err


def step_drop(job: dict) -> dict:
    """The model job["base"] without the images job["names"] (de-registered with their observations; points
    left with < 2 observations go), bundle-adjusted again, written to job["out"] (temp folder, renamed)."""
    import pycolmap

    out = Path(job["out"])
    rec = pycolmap.Reconstruction(job["base"])
    drop = set(job["names"])
    for i in list(rec.reg_image_ids()):
        if rec.image(i).name in drop:
            rec.deregister_frame(rec.image(i).frame_id)
    if rec.num_reg_images() >= 2 and rec.num_points3D() > 0:
        _bundle_adjust(rec, job.get("options", {}))
    _write_model(rec, out)
    return {"registered": int(rec.num_reg_images()), "points": int(rec.num_points3D()), "path": str(out)}


def step_recover(job: dict) -> dict:
    """Re-register images the sanity check dropped (or the mapper left out) against the trusted model
    job["base"]. Candidate poses per image, cheap ones first: (1) absolute pose (COLMAP's
    `register_next_image` on the 2D-3D correspondences its verified matches give with the model's points);
    (2) the table-plane homography with each registered image it matches (`_plane_homography_candidates`:
    the plane known in the model picks the right decomposition and fixes the scale, where (1) and the
    mapper give a mirrored or parallax-free pose); only when a pass of those adds nothing, (3)
    structure-less resectioning (`register_next_structure_less_image`, 2D-2D matches with the registered
    images; a few RANSAC seeds). Each candidate is refined like a merge (`_merged`: all points
    re-triangulated from the database, bundle adjustment) and kept only if, in the refined model, it
    observes >= `min_observations` points at <= `max_error_px` mean reprojection error, no image fails
    the registration sanity check (`splattwin.poses.sanity`), it is not a parallax-free copy of a
    registered camera (`_coincident`) nor, for numbered frames of a walk around the scene
    (job["frame_order"]), out of the walking order (`_out_of_order`). Accepted images are added one by
    one and the passes repeat while they add any (on the cake, frame000096 came back by (2) and then
    frame000069 by (3) with the points 096 brought). Writes the completed model to job["out"] when
    anything was recovered. Returns {"recovered": {name: {"method", "observations"}}, "rejected":
    {name: why, per candidate}, "registered", "path" (if written)}."""
    import pycolmap

    db, root, out = job["db"], job["image_root"], Path(job["out"])
    popts = _set_options(pycolmap.IncrementalPipelineOptions(), job.get("options", {}))
    mopts = popts.get_mapper()
    min_obs, max_err = int(job.get("min_observations", 30)), float(job.get("max_error_px", 2.0))
    with pycolmap.Database.open(db) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        copts = pycolmap.DatabaseCacheOptions()
        copts.min_num_matches = int(popts.min_num_matches)
        cache = pycolmap.DatabaseCache.create(d, copts)
    current, recovered, rejected = pycolmap.Reconstruction(job["base"]), {}, {}
    todo = [n for n in job["names"] if n in ids]
    rejected.update({n: "not in the database" for n in job["names"] if n not in ids})
    costly = False  # structure-less tries (seconds each) only once the cheap ones add nothing
    reasons: dict[str, dict[bool, str]] = {}  # name -> {costly: why its last such pass failed}
    while todo:  # passes until one adds nothing: an image recovered later may carry the next one
        progress = False
        for name in list(todo):
            tried = []
            for method, T in _candidates(cache, current, mopts, db, ids, name, tried, job, costly):
                rec = _merged(db, root, current, {name: T}, job)  # T is in current's frame
                why = _recovery_problem(rec, name, min_obs, max_err, job)
                if why:
                    tried.append(f"{method}: {why}")
                    continue
                current = rec
                recovered[name] = {"method": method, "observations": _observations(rec, name)}
                break
            if name in recovered:
                todo.remove(name)
                progress = True
            else:
                reasons.setdefault(name, {})[costly] = "; ".join(tried)
            emit("progress", done=len(recovered), total=len(job["names"]))
            if progress and costly:
                break  # back to the cheap candidates with the new image's points
        if progress:
            costly = False
        elif costly:
            break
        else:
            costly = True
    for name in todo:
        rejected[name] = "; ".join(r for r in (reasons.get(name, {}).get(False), reasons.get(name, {}).get(True)) if r)
    if recovered:
        _write_model(current, out)
    return {"recovered": recovered, "rejected": rejected, "registered": int(current.num_reg_images()),
            **({"path": str(out)} if recovered else {})}


def _candidates(cache, model, mopts, db: str, ids: dict, name: str, tried: list, job: dict, costly: bool):
    """(method, cam_from_world [3,4]) candidates for `name` in `model`'s frame: absolute pose and the
    table-plane homography with each registered image it matches (most matches first); with `costly`
    structure-less resectioning instead. Failures are appended to `tried`."""
    import pycolmap

    seed = int(job.get("seed", 0))
    tries = [("absolute", seed), ("plane_homography", seed)]
    if costly:
        # structure-less resectioning of a weakly connected image depends on its RANSAC draws (cake
        # frame000069: 11 or 47 observations, depending on the random state): a few seeded tries
        tries = [("structure_less", seed + k) for k in range(int(job.get("structure_less_tries", 3)))]
    for method, s in tries:
        if method == "plane_homography":
            yield from _plane_homography_candidates(model, db, ids, name, tried, job)
            continue
        pycolmap.set_random_seed(s)  # COLMAP's RANSAC draws from a process-wide generator
        mopts.random_seed = s
        if method == "structure_less" and s != seed:
            method = f"structure_less (seed {s})"
        try:
            T = _candidate_pose(cache, model, mopts, ids[name], method.split(" ")[0])
        except (RuntimeError, ValueError) as e:  # a failed COLMAP check: this candidate only
            tried.append(f"{method}: {e}")
            continue
        if T is None:
            tried.append(f"{method}: no pose")
            continue
        yield method, T


def _plane_homography_candidates(model, db: str, ids: dict, name: str, tried: list, job: dict):
    """Poses of `name` from the homography its matches with a registered image induce through the table
    plane. On a nearly planar tabletop (plate, tray, ground) the 2D-2D matches fit a homography, which the
    relative-pose and absolute-pose solvers turn into a mirrored or parallax-free pose; but with the plane
    known in the model (`fit_table_plane`), H = R + t n^T / d has one decomposition whose normal is the
    known one, and d (the plane's distance from the registered camera) fixes the scale of t. A solution
    whose normal is more than `max_normal_deg` (20) off the known one is not used."""
    import numpy as np
    import pycolmap

    from splattwin.errors import InputError
    from splattwin.poses.sfm import result_from_reconstruction
    from splattwin.poses.table import fit_table_plane

    try:
        import cv2
    except ImportError:  # the other candidates still run
        tried.append("plane_homography: OpenCV not available")
        return
    res = result_from_reconstruction(model, [], {}, Path(job["image_root"]))
    if len(res.cameras) < 3:
        return
    try:
        plane = fit_table_plane(res.points_xyz, np.array([c.center for c in res.cameras.values()]),
                                seed=int(job.get("seed", 0)))
    except InputError as e:
        tried.append(f"plane_homography: no table plane ({e.problem})")
        return
    max_normal = float(job.get("max_normal_deg", 20.0))
    min_inliers = int(job.get("min_homography_inliers", 15))
    reg = {model.image(i).name: model.image(i) for i in model.reg_image_ids()}
    with pycolmap.Database.open(db) as d:
        links = []
        for ref in reg:
            m = np.asarray(d.read_two_view_geometry(ids[ref], ids[name]).inlier_matches).reshape(-1, 2)
            if len(m) >= min_inliers:
                links.append((len(m), ref, m))
        links.sort(key=lambda x: (-x[0], x[1]))
        kp = {n: d.read_keypoints(ids[n])[:, :2].astype(np.float64) for n in [name] + [r for _, r, _ in links]}
        cid = d.read_image(ids[name]).camera_id  # the model may not hold the unregistered image
        cam2 = model.camera(cid) if cid in model.cameras else d.read_camera(cid)
    if not links:
        tried.append(f"plane_homography: no registered image with >= {min_inliers} verified matches")
        return
    for _, ref, m in links:
        im = reg[ref]
        T1 = im.cam_from_world().matrix()
        R1, t1 = T1[:, :3], T1[:, 3]
        # the plane n.X + d = 0 (world) in ref's camera frame as n_c.x = dist, dist > 0
        n_c, d_c = -(R1 @ plane.normal), plane.d - plane.normal @ (R1.T @ t1)
        if d_c < 0:
            n_c, d_c = -n_c, -d_c
        cam1 = model.camera(im.camera_id)
        u1 = np.asarray(cam1.cam_from_img(kp[ref][m[:, 0]]), np.float64)[:, :2]
        u2 = np.asarray(cam2.cam_from_img(kp[name][m[:, 1]]), np.float64)[:, :2]
        H, mask = cv2.findHomography(u1, u2, cv2.RANSAC, float(job.get("homography_max_error_px", 3.0))
                                     / float(cam1.mean_focal_length()))
        if H is None or int(mask.sum()) < min_inliers:
            tried.append(f"plane_homography via {ref}: {0 if mask is None else int(mask.sum())} homography inliers")
            continue
        _, Rs, ts, ns = cv2.decomposeHomographyMat(H, np.eye(3))
        off = [float(np.degrees(np.arccos(np.clip(np.ravel(nn) @ n_c, -1, 1)))) for nn in ns]
        k = int(np.argmin(off))
        if off[k] > max_normal:
            tried.append(f"plane_homography via {ref}: no decomposition with the table's normal "
                         f"(best {off[k]:.0f} deg off)")
            continue
        R, t = Rs[k], np.ravel(ts[k]) * d_c  # x2 = R x1 + t, t/d from OpenCV
        yield f"plane_homography via {ref}", np.hstack([R @ R1, (R @ t1 + t)[:, None]])


def _candidate_pose(cache, model, mopts, image_id: int, method: str):
    """cam_from_world [3,4] of `image_id` registered into a copy of `model` by `method`, or None."""
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    try:
        if method == "absolute":
            ok = mapper.register_next_image(mopts, image_id)
        else:
            ok = mapper.register_next_structure_less_image(mopts, image_id)
        return mapper.reconstruction.image(image_id).cam_from_world().matrix() if ok else None
    finally:
        mapper.end_reconstruction(True)


def _observations(rec, name: str) -> int:
    return int(next(rec.image(i) for i in rec.reg_image_ids() if rec.image(i).name == name).num_points3D)


def _recovery_problem(rec, name: str, min_obs: int, max_err: float, job: dict) -> str:
    """Why the re-registered `name` in the refined model `rec` is not trusted ("" if it is)."""
    from splattwin.poses.sanity import SanityOptions, check_registration
    from splattwin.poses.sfm import result_from_reconstruction

    if name not in {rec.image(i).name for i in rec.reg_image_ids()}:
        return "lost in the refinement"
    if not _image_ok(rec, name, min_obs, max_err):
        return f"observes {_observations(rec, name)} points (need >= {min_obs} within {max_err:g} px)"
    res = result_from_reconstruction(rec, [], {}, Path(job["image_root"]))
    obs = {rec.image(i).name: int(rec.image(i).num_points3D) for i in rec.reg_image_ids()}
    chk = check_registration(res.cameras, obs, res.points_xyz, SanityOptions(min_observations=min_obs),
                             seed=int(job.get("seed", 0)))
    if chk.dropped:
        return "fails the registration check: " + "; ".join(f"{n}: {w}" for n, w in sorted(chk.dropped.items()))
    twin = _coincident(res.cameras, name, float(job.get("min_baseline_frac", 0.05)),
                       float(job.get("max_turn_deg", 10.0)))
    if twin:
        return twin
    return _out_of_order(res.cameras, res.points_xyz, name, job.get("frame_order") or [],
                         float(job.get("order_margin_deg", 10.0)), int(job.get("seed", 0)))


def _out_of_order(cameras: dict, points, name: str, order: list[str], margin_deg: float, seed: int) -> str:
    """For frames of a walk around the scene (`order`: the names in capture order): the azimuth of `name`
    about the point the cameras look at (in the table plane) must lie between those of its registered
    predecessor and successor, within `margin_deg`. Applies only when the other registered cameras'
    azimuths advance monotonically with the frame order (< 180 deg per step); "" if it holds or does
    not apply."""
    import numpy as np

    from splattwin.errors import InputError
    from splattwin.poses.sanity import nearest_to_axes
    from splattwin.poses.table import fit_table_plane

    seq = [n for n in order if n in cameras]
    if name not in seq or len(seq) < 5:
        return ""
    k = seq.index(name)
    if k == 0 or k == len(seq) - 1:
        return ""  # an end of the walk: no interval to lie in
    others = [n for n in seq if n != name]
    try:
        plane = fit_table_plane(np.asarray(points, np.float64).reshape(-1, 3),
                                np.array([cameras[n].center for n in others]), seed=seed)
    except InputError:
        return ""
    target = nearest_to_axes([cameras[n] for n in others])
    if target is None:
        return ""
    nrm = plane.normal
    e1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)

    def az(n: str) -> float:
        v = cameras[n].center - target
        return float(np.degrees(np.arctan2(v @ e2, v @ e1)))

    steps = [(az(b) - az(a) + 180.0) % 360.0 - 180.0 for a, b in zip(others, others[1:])]
    sign = np.sign(np.sum(steps))
    if sign == 0 or any(np.sign(st) != sign for st in steps):
        return ""  # not a walk in one direction: no order to check
    prev, nxt = seq[k - 1], seq[k + 1]
    span = ((az(nxt) - az(prev)) * sign) % 360.0
    at = ((az(name) - az(prev)) * sign) % 360.0
    if at <= span + margin_deg or at >= 360.0 - margin_deg:
        return ""
    return (f"out of the capture order: {at:.0f} deg around the scene from {prev}, while {nxt} (the next "
            f"registered frame) is {span:.0f} deg on")


def _coincident(cameras: dict, name: str, min_baseline_frac: float, max_turn_deg: float) -> str:
    """A camera placed (nearly) at another's centre but turned by more than `max_turn_deg`: a hand-held
    capture does not turn in place between views SfM had to register separately, while a homography
    (the plate and tray are nearly planar) is explained by exactly such a pure rotation. Distances are
    relative to the median distance between camera centres. "" if none."""
    import numpy as np

    C = {n: c.center for n, c in cameras.items()}
    others = [n for n in C if n != name]
    if len(others) < 2:
        return ""
    pair = [float(np.linalg.norm(C[a] - C[b])) for i, a in enumerate(list(C)) for b in list(C)[i + 1:]]
    scale = float(np.median(pair)) or 1.0
    for m in others:
        dist = float(np.linalg.norm(C[name] - C[m])) / scale
        R = cameras[name].T_world_cam[:3, :3].T @ cameras[m].T_world_cam[:3, :3]
        turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        if dist < min_baseline_frac and turn > max_turn_deg:
            return (f"placed at the centre of {m} ({dist:.3f} x the median camera distance) but turned "
                    f"{turn:.0f} deg: a parallax-free (homography) registration")
    return ""


def _copy_pose(dst, src, image_id: int) -> None:
    T = src.image(image_id).cam_from_world().matrix()
    _set_pose(dst, image_id, T)


STEPS: dict[str, Callable[[dict], dict]] = {
    "extract": step_extract, "match": step_match, "map": step_map, "triangulate": step_triangulate,
    "merge": step_merge, "drop": step_drop, "recover": step_recover,
}


def _die_with_parent() -> None:
    """Linux: get SIGKILL when the parent dies, so a killed run leaves no orphan burning the CPU."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() == 1:  # the parent died before prctl took effect
            os._exit(1)
    except OSError:
        pass


def _quiet_sigterm() -> None:
    """SIGTERM (the parent's `terminate`, or Slurm/Kubernetes/docker signalling every process of a job)
    ends this process at once and silently: the default action. Importing pycolmap installs glog's
    failure-signal handler for SIGTERM at the C level (Python's `getsignal` still says SIG_DFL), which
    printed a ~30-line C stack trace ("*** Aborted at ...") before dying; `signal.signal` sets the
    handler again at the C level whatever Python believes (as `interrupt._reclaim_sigterm` does). Not a
    Python-level function: it would only run once pycolmap's C++ returns to the interpreter, which
    mapping and triangulation do not do for minutes. The parent cleans up what the step half-wrote."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    _die_with_parent()
    # Ctrl-C in a terminal reaches the whole process group; the parent decides (it terminates us).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    job = json.loads(Path(argv[0]).read_text())
    import pycolmap

    _quiet_sigterm()
    pycolmap.logging.minloglevel = int(job.get("log_level", 2))
    try:
        result = STEPS[job["step"]](job)
    except Exception as e:  # reported to the parent, which raises it with the step's context
        emit("error", message=f"{type(e).__name__}: {e}")
        return 1
    emit("result", **result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
