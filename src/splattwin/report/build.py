"""The twin's HTML report: inputs, reconstruction quality, semantics, geometry, robot task, timings,
versions — with pictures, in one self-contained file (TWIN/report/index.html).

Every section reads the artifacts its stage wrote; a stage that did not run gets a one-line note
instead of a section full of holes.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.report.html import Report, Section
from splattwin.wording import plural

log = logging.getLogger(__name__)


def picture(twin: Path, path: Path) -> Path | None:
    """`path`, a picture the report embeds from the twin folder, when it is a file inside the twin with its
    symbolic links resolved; else None. A received twin's `poses/cameras.png` linked to an image elsewhere
    (`/home/me/private.png`, `../../x.png`) put that file, base64, into the report that is then shared: such a
    link is named in a warning and left out."""
    from splattwin.paths import is_inside

    if not path.is_file():
        return None
    if not is_inside(path, twin):
        log.warning("report: %s leads outside the twin folder %s (a symbolic link): not embedded", path, twin)
        return None
    return path


def _json(path: Path):
    """A stage's JSON artifact, or None when that stage did not run (or left nothing readable). Read within the
    record limit: the twin may be someone else's, and 1 GiB of JSON (the limit meant for COCO files) costs ~10 GB
    to parse. Every stage record is a JSON object: any other value (a list, a number: a hand-edited or received
    twin) counts as unreadable too."""
    rec = io.read_record(path)
    if rec is not None and not isinstance(rec, dict):
        log.warning("report: %s is not a JSON object: left out", path)
        return None
    return rec


def render_meshes(meshes: list, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int,
                  light_dir=(0.3, -0.4, 0.85)) -> np.ndarray:
    """Ray-cast Lambertian render of world-frame meshes [(V [n,3], F [m,3], rgb [3] in 0..1[, alpha])] →
    HxWx3. A mesh with alpha < 1 is translucent: its nearest surface in front of the opaque scene is
    blended over it (one layer: overlapping translucent meshes show the nearest).

    Open3D's RaycastingScene needs no OpenGL context, so this works on headless CI machines.
    """
    import open3d as o3d

    d = np.asarray(light_dir, np.float32)
    d /= np.linalg.norm(d)

    def cast(group):
        scene = o3d.t.geometry.RaycastingScene()
        for V, F, *_ in group:
            m = o3d.t.geometry.TriangleMesh()
            m.vertex.positions = o3d.core.Tensor(np.asarray(V, np.float32))
            m.triangle.indices = o3d.core.Tensor(np.asarray(F, np.int32))
            scene.add_triangles(m)
        rays = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(T_world_cam)),
                                         width, height)
        hit = scene.cast_rays(rays)
        n = hit["primitive_normals"].numpy()
        ray_dir = rays.numpy()[..., 3:]
        n = np.where((np.sum(n * ray_dir, axis=-1) > 0)[..., None], -n, n)  # face the camera
        shade = 0.35 + 0.65 * np.clip(np.sum(n * d, axis=-1), 0, 1)
        t = hit["t_hit"].numpy()
        pal = np.asarray([m[2] for m in group] + [(1, 1, 1)], np.float32)
        miss = ~np.isfinite(t)
        img = pal[np.where(miss, len(group), hit["geometry_ids"].numpy())] * shade[..., None]
        img[miss] = 1.0
        return img, np.where(miss, np.inf, t), hit["geometry_ids"].numpy()

    solid = [m for m in meshes if len(m) < 4 or m[3] >= 1.0]
    clear = [m for m in meshes if len(m) >= 4 and m[3] < 1.0]
    if solid:
        img, t_solid, _ = cast(solid)
    else:
        img, t_solid = np.ones((height, width, 3), np.float32), np.full((height, width), np.inf, np.float32)
    if clear:
        over, t_clear, gid = cast(clear)
        front = np.isfinite(t_clear) & (t_clear < t_solid)
        alpha = np.asarray([m[3] for m in clear], np.float32)[np.where(front, gid, 0)] * front
        img = img * (1 - alpha[..., None]) + over * alpha[..., None]
    return img


def _twin_meshes(twin_dir: Path, parts: list | None = None) -> list:
    """World-frame collision parts [(V, F, rgb, alpha)] in their label colours (the background in table
    colour; an unusable object's obstacle box translucent red, as `collision_parts` gives it). parts: the
    twin's `collision_parts` when already loaded."""
    from splattwin.playback.view_model import collision_parts
    from splattwin.twin.manifest import Manifest

    if parts is None:
        parts = collision_parts(twin_dir, Manifest.load(twin_dir))
    return [(p.world_vertices(), p.faces, (0.75, 0.72, 0.66) if p.owner == "background" else
             tuple(c / 255.0 for c in p.color), p.opacity if p.obstacle and p.opacity is not None else 1.0)
            for p in parts]


COLLISION_VIEW_SIDE = 480   # px: longest side of a collision picture's photo and render


def _collision_views(twin_dir: Path, frames: list) -> list[tuple[str, np.ndarray]]:
    """[(view name, picture)]: each capture frame's photo beside the collision parts rendered from its camera
    at the same size (at most `COLLISION_VIEW_SIDE` px: ray casting a 4032x3024 photo's camera is slow and
    makes a huge picture), with a key of the objects' colours (the failure text of a tipped placement
    sends the user to an object's mesh here)."""
    from splattwin.capture import load_image
    from splattwin.pictures import fit_height, legend_strip, side_by_side
    from splattwin.playback.view_model import collision_parts
    from splattwin.twin.manifest import Manifest

    parts = collision_parts(twin_dir, Manifest.load(twin_dir))
    meshes = _twin_meshes(twin_dir, parts)
    key = {}
    for p, m in zip(parts, meshes):
        key.setdefault("table / background" if p.owner == "background" else p.owner,
                       tuple(round(255 * c) for c in m[2]))
    out = []
    for fr in frames:
        cam = fr.camera
        cam = cam.scaled(min(1.0, COLLISION_VIEW_SIDE / max(cam.width, cam.height)))
        try:
            render = render_meshes(meshes, cam.T_world_cam, cam.K, cam.width, cam.height)
        except Exception as e:  # a picture must never fail the report
            log.warning("mesh render failed: %s", e)
            continue
        try:
            photo = fit_height(load_image(fr.image_path), cam.height)
            pics = [photo, render] if photo.shape[:2] == render.shape[:2] else [render]
        except InputError:   # the photos stayed with the capture: the render alone
            pics = [render]
        pics.append(legend_strip(list(key.items()), cam.height))
        out.append((fr.name, side_by_side(pics)))
    return out


# the pipeline's stages in order (`splattwin.pipeline.options.STAGES`: the report may not import the
# pipeline, a layer above it; tests/pipeline checks the two agree) and the files of each that the report shows
PIPELINE_STAGES = ("scene", "poses", "splats", "semantics", "twin", "robot", "report")
_SHOWN = (("splats", ("splat/eval/metrics.json",)), ("semantics", ("semantics/fusion.json",)),
          ("twin", ("twin.json", "geometry_metrics.json")))


def unvouched(twin: str | Path) -> str | None:
    """When TWIN/pipeline.json exists (a `build` made this folder) and does not vouch for the files the
    report shows, a sentence saying so (None when it does, or when there is none: stages run by hand):
    - a stage's recorded outputs no longer match the files (`splattwin.hashing.changed_outputs`: e.g.
      `splattwin train` run by hand into the twin rewrote splat/point_cloud.ply): the held-out metrics,
      semantics and twin shown were made from the earlier files. The robot stage is left out (`splattwin
      plan` rewrites its results and records itself; `robot.outputs.results_twin` checks those).
    - no record of a stage whose files are there (`build --until splats`, or a build stopped midway: the
      runner drops the records of every stage from the one it re-runs, and keeps the later stages'
      folders, whose caches resume work): those files are an earlier build's."""
    from splattwin.hashing import DIGEST_CACHE, DigestCache, changed_outputs

    twin = Path(twin)
    if not (twin / "pipeline.json").is_file():
        return None
    state = _json(twin / "pipeline.json")
    state = state if isinstance(state, dict) else {}
    notes = []
    cache = DigestCache(twin / DIGEST_CACHE)   # the build's: a stat() per unchanged file (read, never saved here)
    for stage in PIPELINE_STAGES[:PIPELINE_STAGES.index("robot")]:
        rec = state.get(stage)
        files = changed_outputs(twin, rec, cache) if isinstance(rec, dict) else []
        if files:
            shown = PIPELINE_STAGES[PIPELINE_STAGES.index(stage):PIPELINE_STAGES.index("robot")]
            what = [w for n, w in (("splats", "held-out metrics"), ("semantics", "semantics"), ("twin", "twin"))
                    if n in shown]
            which = f"stage {stage}" if len(shown) == 1 else f"stages {shown[0]}..{shown[-1]}"
            notes.append(f"{', '.join(files)} (stage {stage}) no longer {'matches' if len(files) == 1 else 'match'} "
                         f"what the build recorded: rewritten since (by a command run by hand into this twin, "
                         f"e.g. `splattwin train`?), so nothing vouches that the results of "
                         f"{which} shown here ({', '.join(what)}) were made from "
                         f"{'it' if len(files) == 1 else 'them'} (run `splattwin build` again to bring them up to date)")
            break   # every later stage's results depend on this one's
    stale = [(stage, rel) for stage, files in _SHOWN for rel in files
             if stage not in state and (twin / rel).is_file()]
    if stale:
        done = [i for i, n in enumerate(PIPELINE_STAGES) if n in state]
        later = PIPELINE_STAGES[(max(done) + 1) if done else 0:] or tuple(stage for stage, _ in stale)
        last = f"after the last {PIPELINE_STAGES[max(done)]}" if done else "in the last build (pipeline.json records none)"
        files = [rel for _, rel in stale]
        notes.append(f"{', '.join(files)} {'is' if len(files) == 1 else 'are'} from an earlier build: stages "
                     f"{later[0]}..{later[-1]} did not run {last}, so {'it' if len(files) == 1 else 'they'} may "
                     f"not match the newer outputs shown beside {'it' if len(files) == 1 else 'them'} (run "
                     f"`splattwin build` again without --until to bring them up to date)")
    return ". ".join(notes) or None


def _poses_frame(twin: Path):
    """The poses stage's frame (TWIN/poses/frame.json), or None (absent or unreadable)."""
    from splattwin.poses.twin_frame import load_frame

    p = twin / "poses" / "frame.json"
    try:
        return load_frame(p) if p.is_file() else None
    except InputError:
        return None


STAGE_TIME_KPI = "stage time, sum (s)"
THUMB_HEIGHT = 240   # px: the "a few input views" strip (4 thumbnails side by side)


def stage_time_sum(timings: dict) -> float:
    """The report's and the build's terminal line's one stage-time figure: the sum of the stages' recorded
    seconds without the report stage's own (it is being written when the report takes the figure). A stage
    a build found up to date counts the seconds of the run that made it. Not a run's wall-clock time: that
    also has the pre-flight, the input hashing and the report, and a skipped stage costs it ~0 s."""
    return float(sum(v for k, v in timings.items() if k != "report" and isinstance(v, (int, float))))


# TWIN/pipeline.json's robot record: the `splattwin plan` run that rewrote TWIN/robot after the build
# {"seconds", "peak_rss_gib", "finished"}. The runner replaces the whole record when its robot stage runs again
# (which a plan's rewritten results.json makes it do: its recorded digests no longer match).
PLAN_RUN = "plan"


def record_plan_run(twin_dir: str | Path, seconds: float, peak_rss_gib: float) -> bool:
    """Record a `splattwin plan` run that wrote TWIN/robot (seconds: its run, s; peak_rss_gib: GiB) in
    TWIN/pipeline.json's robot record (`PLAN_RUN`), beside the build's own figures, so that the report's
    timings show the run whose results it shows. Called inside the twin's lock (plan's). Nothing when there
    is no build record of the robot stage (no pipeline.json, or a build --until twin): returns whether
    it recorded. An unreadable pipeline.json is left as it is (the report then shows no timings)."""
    import time

    path = Path(twin_dir) / "pipeline.json"
    state = io.read_record(path)
    if not isinstance(state, dict) or not isinstance(state.get("robot"), dict):
        return False
    state["robot"][PLAN_RUN] = {"seconds": float(seconds), "peak_rss_gib": float(peak_rss_gib),
                                "finished": time.time()}
    io.write_json(path, state)
    return True


def _plan_run(rec: dict) -> dict | None:
    """A stage record's `PLAN_RUN` entry when it is well formed (numbers), else None."""
    plan = rec.get(PLAN_RUN)
    ok = isinstance(plan, dict) and all(isinstance(plan.get(k), (int, float)) and not isinstance(plan.get(k), bool)
                                        for k in ("seconds", "peak_rss_gib"))
    return plan if ok else None


def build_report(twin_dir: str | Path, timings: dict | None = None, peak_rss_gib: dict | None = None,
                 options=None, skipped: list[str] | None = None) -> Path:
    """Write TWIN/report/index.html. options: `report.options.ReportOptions` (the task video). timings /
    peak_rss_gib: {stage: value} of the build writing it (default: TWIN/pipeline.json's records); skipped:
    the stages that build found up to date (their seconds are an earlier run's; None: not known)."""
    from splattwin.twin.manifest import Manifest

    twin = Path(twin_dir)
    if not twin.is_dir():   # a mistyped path made a folder holding only an empty report (the command checked it)
        raise InputError("twin folder does not exist", twin)
    man = Manifest.load(twin) if (twin / "twin.json").is_file() else None
    fr = man.frame if man else _poses_frame(twin)   # a folder built --until splats has the poses' frame
    rep = Report(f"splattwin twin — {twin.resolve().name}",
                 f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} · frame: "
                 + (fr.summary() if fr else "n/a"))
    poses = _json(twin / "poses" / "poses_report.json")
    ev = _json(twin / "splat" / "eval" / "metrics.json")
    fusion = _json(twin / "semantics" / "fusion.json")
    geo = _json(twin / "geometry_metrics.json")
    robot = _json(twin / "robot" / "results.json")
    robot_stale = None
    if robot is not None and man is not None:
        from splattwin.robot.outputs import results_twin

        # results of `plan` on an earlier twin (rebuilt since by hand: `geometry`, `build` without --task)
        # are not this twin's: no robot figures, a note instead
        robot_stale = results_twin(robot, twin)
        if robot_stale is not None:
            log.warning("report: robot results not shown: %s", robot_stale)
            robot = None
    state = _json(twin / "pipeline.json") or {}
    if not isinstance(state, dict):
        state = {}
    state = {k: v for k, v in state.items() if isinstance(v, dict)}
    # a `splattwin plan` run since the build rewrote TWIN/robot: the robot row is that run's, as the robot
    # section shows its results (the other stages keep the build's figures)
    plan = _plan_run(state.get("robot", {}))
    if plan is not None:
        timings = {**(timings or {k: v.get("seconds", 0.0) for k, v in state.items()}), "robot": plan["seconds"]}
        peak_rss_gib = {**(peak_rss_gib or {k: v.get("peak_rss_gib", 0.0) for k, v in state.items()}),
                        "robot": plan["peak_rss_gib"]}

    head = rep.section("Summary")
    kpis: dict = {}
    notes = [_guarded_kpis(kpis, rel, fn, rec) for rel, fn, rec in (
        ("splat/eval/metrics.json", _eval_kpis, ev), ("semantics/fusion.json", _fusion_kpis, fusion),
        ("geometry_metrics.json", _geometry_kpis, geo), ("robot/results.json", _robot_kpis, robot))]
    tt = timings or {k: v.get("seconds", 0.0) for k, v in state.items()}
    if tt:
        kpis[STAGE_TIME_KPI] = round(stage_time_sum(tt), 1)
    if man and not man.frame.scaled:
        kpis["scale"] = "unscaled"
    head.kpis(kpis)
    for note in filter(None, notes):
        head.text(note)
    stale = unvouched(twin)
    if stale:
        log.warning("report: %s", stale)
        head.text(f"WARNING: {stale}.")
    if man and not man.frame.scaled:
        from splattwin.twin.manifest import unscaled_note

        head.text(f"{unscaled_note(man.frame)} The geometry's thresholds were derived from the capture "
                  f"(nominal metre {man.frame.nominal_metre or 'n/a'} units); robot planning refuses this twin.")

    _guarded(_inputs_section, rep.section("Inputs and camera poses"), twin, poses, man)
    _guarded(_recon_section, rep.section("Reconstruction (3D Gaussian Splatting)"), twin, ev)
    _guarded(_semantics_section, rep.section("Semantic objects (visibility-aware fusion)"), twin, fusion)
    _guarded(_geometry_section, rep.section("Collision geometry"), twin, man, geo)
    _guarded(_robot_section, rep.section("Robot task in physics (Franka Panda, MuJoCo)"), twin, robot, robot_stale,
             man)
    if robot and "error" not in robot:
        from splattwin.report.playback import playback_section

        _guarded(playback_section, rep.section("The task in motion (photoreal twin)"), twin, options)

    t = rep.section("Timings and memory per stage")
    rows = []
    for name, rec in state.items():
        row = [name, (timings or {}).get(name, rec.get("seconds", 0.0)),
               (peak_rss_gib or {}).get(name, rec.get("peak_rss_gib", 0.0))]
        run = ("splattwin plan, after the build" if name == "robot" and plan is not None
               else "up to date: an earlier build's seconds" if skipped is not None and name in skipped
               else "this build")
        rows.append(row + ([run] if skipped is not None else []))
    if rows:
        t.table(["stage", "seconds", "peak RSS (GiB)"] + (["run"] if skipped is not None else []), rows)
        t.text(f"The summary's '{STAGE_TIME_KPI.split(' (')[0]}' ({stage_time_sum(tt):.1f} s) adds up these "
               f"stages' seconds without the report stage's own (a stage found up to date counts the run that "
               f"made it). The build's terminal line 'total' is the wall-clock time of that one run instead: "
               f"pre-flight, input hashing and the report included, a skipped stage ~0 s; it gives this figure "
               f"beside it.")
        if plan is not None:
            fin, built = plan.get("finished"), state["robot"].get("seconds")
            try:
                when = f" of {_dt.datetime.fromtimestamp(fin).strftime('%Y-%m-%d %H:%M')}"
            except (TypeError, ValueError, OverflowError, OSError):   # not a time: left out
                when = ""
            took = (f"; the build's robot stage took {built:.1f} s"
                    if isinstance(built, (int, float)) and not isinstance(built, bool) else "")
            t.text(f"robot: the seconds and memory of the `splattwin plan` run{when}, whose results this report "
                   f"shows{took}.")
    else:
        t.text("no pipeline record (stages run by hand)")
    if man and man.timings:
        t.table(["geometry step", "seconds"], [[k, v] for k, v in man.timings.items()])

    v = rep.section("Versions and options")
    if man:
        v.table(["package", "version"], sorted(man.versions.items()))
        if not man.frame.scaled and isinstance((man.config or {}).get("geometry"), dict):
            # the two geometry blocks below differ by the nominal metre: bare numbers, read as metres
            nm = man.frame.nominal_metre
            v.text("units: \"geometry\" and \"depth_carving\" hold the lengths the twin stage used, in the twin's "
                   "SfM units (the metre values given, under \"build\" → \"geometry\", times the nominal metre"
                   + (f" {nm:.4g} units" if isinstance(nm, (int, float)) else "") + "); \"build\" holds the "
                   "options as given, in metres.")
        v.pre(json.dumps(_config_shown(man.config, robot), indent=2, default=str)[:20000])
    return rep.save(twin / "report" / "index.html")


def _config_shown(config: dict, robot: dict | None) -> dict:
    """twin.json's config with `build.robot` replaced by the options of the robot run whose results the
    report shows (robot/results.json `options`): twin.json records the robot options the build held when
    its twin stage ran, and a later `build --task ...` (twin stage skipped) or `plan` used others."""
    ran = robot.get("options") if isinstance(robot, dict) else None
    if not isinstance(ran, dict) or not isinstance(config.get("build"), dict):
        return config
    return {**config, "build": {**config["build"], "robot": {"(from robot/results.json)": True, **ran}}}


def _guarded(fn, sec: Section, *args) -> None:
    """A section from a stage's artifacts; artifacts of the wrong shape (a hand-edited or received twin)
    give a one-line note in that section instead of failing the whole report."""
    try:
        fn(sec, *args)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        log.warning("report section %r: malformed artifact (%s: %s)", sec.title, type(e).__name__, e)
        sec.text(f"this section could not be built from the twin's files ({type(e).__name__}: {str(e)[:200]})")


def _guarded_kpis(kpis: dict, rel: str, fn, rec: dict | None) -> str | None:
    """kpis updated with `fn(rec)`, the summary figures of the record TWIN/`rel`. A record of the wrong shape (a
    hand-edited or received twin: a string for a number, a list for a table) leaves its figures out and gives
    the note naming the file that is returned, as `_guarded` does for a section, instead of failing the whole
    report."""
    if not rec:
        return None
    try:
        kpis.update(fn(rec))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        log.warning("report summary: %s is malformed (%s: %s); its figures are left out", rel, type(e).__name__, e)
        return f"{rel} is malformed ({type(e).__name__}: {str(e)[:200]}): its figures are left out of the summary."
    return None


def _eval_kpis(ev: dict) -> dict:
    """The summary's figures of splat/eval/metrics.json: PSNR (dB) and SSIM of its split."""
    masked = ", masked" if _masked(ev) else ""
    out = {f"PSNR {ev['split']}{masked} (dB)": round(ev["mean_psnr"], 2)}
    if ev.get("headline") == "aligned" and isinstance(ev.get("mean_psnr_as_given"), (int, float)):
        out[f"PSNR {ev['split']}, poses as given (dB)"] = round(ev["mean_psnr_as_given"], 2)
    out[f"SSIM {ev['split']}{masked}"] = round(ev["mean_ssim"], 4)
    return out


def _fusion_kpis(fusion: dict) -> dict:
    """The summary's figure of semantics/fusion.json: the held-out mIoU (vs the ground truth, else the 2D masks)."""
    if fusion.get("miou_heldout") is not None:
        return {"mIoU held-out": round(fusion["miou_heldout"], 3)}
    if fusion.get("miou_heldout_masks") is not None:
        return {"mIoU held-out vs 2D masks": round(fusion["miou_heldout_masks"], 3)}
    return {}


def _geometry_kpis(geo: dict) -> dict:
    """The summary's figure of geometry_metrics.json: the lowest object F1 at 5 mm."""
    return {"F1 @5 mm (min)": round(min(v["f1"] for v in geo.values()), 3)}


def _robot_kpis(robot: dict) -> dict:
    """The summary's figures of robot/results.json: task success, real-arm files written, trial successes."""
    if "error" in robot:
        return {"task success": False}
    out = {"task success": bool(robot["nominal"]["success"])}
    if isinstance(robot.get("real_robot"), dict):
        out["real-arm files"] = bool(robot["real_robot"].get("written"))
    if robot.get("trials"):
        out["trials"] = f"{robot['trials']['successes']}/{robot['trials']['trials']}"
    return out


def _inputs_section(sec: Section, twin: Path, poses: dict | None, man) -> None:
    from splattwin.capture import load_dataset, load_image
    from splattwin.pictures import fit_height, side_by_side

    tj = twin / "poses" / "transforms.json"
    if not tj.is_file():
        sec.text("poses stage not run")
        return
    try:
        ds = load_dataset(tj, validate=False)
    except InputError as e:  # e.g. a twin of an earlier version whose images stayed with the capture
        sec.text(f"the input views are not available ({e}); the twin itself does not need them")
        return
    sizes = sorted({(f.camera.width, f.camera.height) for f in ds.frames})
    at = f"{sizes[0][0]}×{sizes[0][1]}" if len(sizes) == 1 else f"{len(sizes)} image sizes ({', '.join(f'{w}×{h}' for w, h in sizes[:4])}{', ...' if len(sizes) > 4 else ''})"
    sec.text(f"{plural(len(ds.train()), 'training view')} and {plural(len(ds.heldout()), 'held-out view')} at {at}.")
    _heldout_rows(sec, ds.meta.get("heldout"), [f.name for f in ds.heldout()])
    if poses:
        rows = [[k, poses[k]] for k in ("method", "registered", "total") if k in poses]
        # the poses stage writes `mean_reproj_error` (px) and `timings` (s per SfM step, `poses/sfm.py`);
        # `mean_reproj_error_px` / `sfm_s` are older names, read when a file has them
        err = poses.get("mean_reproj_error", poses.get("mean_reproj_error_px"))
        if isinstance(err, (int, float)) and not isinstance(err, bool):
            rows.append(["mean reprojection error (px)", round(float(err), 3)])
        if isinstance(poses.get("num_points"), int):
            rows.append(["sparse points", poses["num_points"]])
        tim = poses.get("timings")
        steps = {k: v for k, v in tim.items() if k != "cpu" and isinstance(v, (int, float))} \
            if isinstance(tim, dict) else {}
        sfm_s = sum(steps.values()) if steps else poses.get("sfm_s")
        if isinstance(sfm_s, (int, float)) and not isinstance(sfm_s, bool):
            rows.append(["SfM time (s)" + (f": {', '.join(steps)}" if steps else ""), round(float(sfm_s), 2)])
        exp = poses.get("exposure")
        if isinstance(exp, dict):
            rows.append(["exposure / white balance between the photos", _exposure_text(exp)])
        if rows:
            sec.table(["pose estimation", "value"], rows)
    if man:
        f = man.frame
        unc = f.scale_uncertainty_rel
        rows = [["source", f.source], ["metric", f.scaled], ["units", f.units],
                *([["nominal metre (units)", f.nominal_metre]] if not f.scaled else []),
                ["scale uncertainty (1 sigma)", f"{100 * unc:.2g} %" if isinstance(unc, (int, float)) else "n/a"],
                *([["definition", f.description]] if f.description else [])]
        ds_fit = poses.get("depth_scale") if poses else None
        if isinstance(ds_fit, dict) and isinstance(ds_fit.get("scale"), (int, float)):   # SfM + depth images
            rows.append(["scale from the depth images", f"x {ds_fit['scale']:.6g} (SfM unit -> m), "
                                                        f"{ds_fit.get('readings')} readings over {ds_fit.get('views')} "
                                                        f"views, spread {100 * float(ds_fit.get('spread_rel', 0)):.2g} %"])
        elif isinstance(ds_fit, dict) and isinstance(ds_fit.get("error"), str):
            rows.append(["scale from the depth images", f"none: {ds_fit['error']}"])
        sec.table(["twin frame", "value"], rows)
    # thumbnails: full-size phone photos (4032x3024) side by side made a picture of many megabytes
    thumbs = [fit_height(load_image(fr.image_path), THUMB_HEIGHT)
              for fr in ds.train()[:: max(1, len(ds.train()) // 4)][:4]]
    if thumbs:
        sec.image(side_by_side(thumbs), caption="a few input views", photo=True)
    if picture(twin, twin / "poses" / "cameras.png"):
        sec.image(twin / "poses" / "cameras.png", caption="camera poses and sparse points", width=520,
                  photo=False)   # a plot: lines and text kept exact


def _exposure_text(rec: dict) -> str:
    """The poses stage's exposure check (`splattwin.poses.exposure`) in one cell."""
    if isinstance(rec.get("error"), str):
        return f"not measured: {rec['error']}"
    spread, thr = rec.get("spread_pct"), rec.get("threshold_pct")
    if not isinstance(spread, (int, float)) or isinstance(spread, bool):
        return "not recorded"
    off = [str(n) for n in rec.get("images_off") or []] if isinstance(rec.get("images_off"), list) else []
    text = f"gains differ by up to {spread:.1f} % (threshold {thr} %)"
    if off:
        text += f"; beyond it: {', '.join(off[:12])}{' ...' if len(off) > 12 else ''}"
    return text


def _appearance_text(rec) -> str | None:
    """train.json's appearance decision (`splat.appearance.decide`) in one line, None when not recorded."""
    if not isinstance(rec, dict) or not isinstance(rec.get("decision"), str):
        return None
    mode, why = rec.get("mode"), {
        "auto": "turned on by --splat.appearance auto: the poses stage found the photos' exposure / white balance "
                "differ",
        "suggested": "although the poses stage found the photos' exposure / white balance differ: "
                     "--splat.appearance gain (or auto) learns a correction",
        "explicit": "as asked", "none": "off: no exposure difference found"}.get(rec["decision"], rec["decision"])
    start = ""
    if mode != "off" and rec.get("init") == "measured":
        start = f"; started at the poses stage's measured gains ({rec.get('init_views')} views)"
    elif mode != "off" and rec.get("init") == "identity":
        start = f"; started at gain 1 ({rec.get('init_why') or 'no measured gains'})"
    return (f"per-image colour correction (appearance): {mode} ({why}){start}; held-out views are rendered "
            f"without a correction, and the right-half figures fit one on each view's left half")


def _heldout_rows(sec: Section, rec, views: list) -> None:
    """Which views are held out and by which rule (`splattwin.poses.holdout`)."""
    rule = rec.get("rule") if isinstance(rec, dict) else None
    names = [str(v) for v in views][:40]
    sec.table(["held-out views", "value"], [["rule", str(rule or "the capture's own split")],
                                            ["views", (", ".join(names) + (" ..." if len(views) > 40 else ""))
                                             if names else "none"]])


def length_text(values, scaled: bool, sep: str = " × ") -> str:
    """Lengths for display: centimetres in a metric twin; an unscaled twin's are SfM units, never cm."""
    if scaled:
        return sep.join(f"{x * 100:.1f}" for x in values) + " cm"
    return sep.join(f"{x:.3g}" for x in values) + " units (SfM, unscaled)"


def _masked(ev: dict | None) -> dict | None:
    """metrics.json `loss_masks` when the evaluation left out loss-masked pixels, else None."""
    lm = ev.get("loss_masks") if isinstance(ev, dict) else None
    return lm if isinstance(lm, dict) and lm.get("applied") else None


def _aligned_note(ev: dict) -> str:
    """With pose refinement the headline figure is at the held-out poses aligned to their images (eval.py)."""
    if ev.get("headline") != "aligned":
        return ""
    given = ev.get("mean_psnr_as_given")
    given = f"; at the poses as given {given:.2f} dB" if isinstance(given, (int, float)) else ""
    return (" with each view's pose first aligned to its image, the splats fixed (the training refined its "
            f"poses; the held-out poses share their errors){given}")


def _recon_section(sec: Section, twin: Path, ev: dict | None) -> None:
    if not ev:
        sec.text("splat stage not run")
        return
    legend = str(ev.get("legend", "ground truth | render | error")).strip()
    legend = legend[len("images:"):].strip() if legend.lower().startswith("images:") else legend
    lm = _masked(ev)
    tj = _json(twin / "splat" / "train.json")
    app = _appearance_text(tj.get("appearance") if isinstance(tj, dict) else None)
    if app:
        sec.text(app + ".")
    sec.text(f"{ev['gaussians']} Gaussians; {ev['split']} views: mean PSNR {ev['mean_psnr']:.2f} dB, "
             f"SSIM {ev['mean_ssim']:.4f}" + (" (masked: over the pixels the capture's loss masks keep)" if lm else "")
             + _aligned_note(ev) + f". Images: {legend}.")
    if lm:
        views = lm.get("views") if isinstance(lm.get("views"), list) else []
        sec.text(f"loss masks applied (nerfstudio mask_path) to {plural(len(views), 'evaluated view')}"
                 f"{': ' + ', '.join(map(str, views[:20])) if views else ''}: {lm.get('protocol', '')} "
                 f"These figures are not comparable with an evaluation over whole images (splatfacto's).")
    er = ev.get("eval_resolution")
    if isinstance(er, dict):
        what = {"training": "the training resolution", "full": "full resolution", "given": "a given resolution"}
        # each rule from its own record: eval's "how" is the evaluation's rule (full size under
        # --eval-full-resolution), not the training's, which only train.json records
        tr = _json(twin / "splat" / "train.json")
        tres = tr.get("resolution") if isinstance(tr, dict) else None
        sec.table(["evaluation", "value"], [
            ["evaluated at", f"{er.get('sizes', '?')} ({what.get(str(er.get('mode')), str(er.get('mode')))})"],
            ["image size", str(er.get("full_sizes", "?"))],
            ["training resolution rule", str(tres.get("how", "?")) if isinstance(tres, dict) else "not recorded"],
            ["evaluation resolution rule", str(er.get("how", "?"))]])
    if isinstance(ev.get("heldout"), dict):
        _heldout_rows(sec, ev["heldout"], ev["heldout"].get("views") or [])
    if any("covered_frac" in r for r in ev["views"]):
        # how much of each held-out view the training photos saw at all (frustum test): the rest is content
        # no photo holds, reported apart so that a sparse capture's extrapolation is not read as blur
        sec.table(["view", "PSNR (dB)", "SSIM", "seen by training views (%)", "PSNR seen (dB)", "PSNR unseen (dB)"],
                  [[r["name"], r["psnr"], r["ssim"], round(100 * r.get("covered_frac", float("nan")), 1),
                    "-" if r.get("psnr_covered") is None else r["psnr_covered"],
                    "-" if r.get("psnr_uncovered") is None else r["psnr_uncovered"]] for r in ev["views"]])
    else:
        sec.table(["view", "PSNR (dB)", "SSIM"], [[r["name"], r["psnr"], r["ssim"]] for r in ev["views"]])
    for r in ev["views"][:5]:
        if not r.get("image"):
            continue
        from splattwin.paths import confined

        p = confined(twin / "splat" / "eval", r["image"], twin / "splat" / "eval" / "metrics.json", "image")
        if picture(twin, p):   # (confined to splat/eval, which may itself be a link out of the twin)
            sec.image(p, caption=f"{r['name']}: ground truth | render | error", photo=True)
    if picture(twin, twin / "splat" / "transients.png"):   # a photo collection: what the loss left out
        sec.image(twin / "splat" / "transients.png", caption="transient masks (red): what training left out of "
                  "each photo as seen in that photo only (people, vehicles; `--splat.robust-quantile`)", width=720,
                  photo=True)


def _semantics_section(sec: Section, twin: Path, fusion: dict | None) -> None:
    if not fusion:
        sec.text("semantics stage not run")
        return
    sec.text(f"method: {fusion.get('method', 'visibility-aware')}; κ = {fusion['options']['kappa']}, "
             f"{fusion['options']['iters']} refinement rounds; {fusion.get('n_views_fused', '?')} views fused.")
    sec.table(["object", "label", "Gaussians"], [[o["name"], o["label"], o["n_gaussians"]] for o in fusion["objects"]])
    m = [[k.replace("miou_", "mIoU ").replace("_masks", " vs its 2D masks").replace("_", " "), fusion[k]]
         for k in sorted(fusion) if k.startswith("miou") and isinstance(fusion[k], (int, float))]
    for k in ("consistency", "ghost_index"):
        if k in fusion:
            m.append([k, fusion[k]])
    if m:
        sec.table(["metric", "value"], m)
    if fusion.get("kappa_sweep"):
        sec.text("κ sweep (τ = N/κ): 3D projection consistency (% of labelled points with N_fg/N ≥ 0.8) and ghost index (%), "
                 "each κ's consensus before the KNN boundary smoothing (so the row of the κ used may differ a little "
                 "from the figures above, which are after it).")
        sec.table(["κ", "consistency (%)", "ghost index (%)"],
                  [[r["kappa"], r["consistency"], r["ghost_index"]] for r in fusion["kappa_sweep"]])
    heldout = set(fusion.get("miou_heldout_masks_views") or []) | _heldout_names(twin)
    views = fusion.get("label_map_views")
    # this fusion's views, not whatever pictures lie there (an older fusion.json without the list: all)
    shown = {v for v in views if isinstance(v, str)} if isinstance(views, list) else None

    def ours(p: Path) -> bool:
        return shown is None or p.stem in shown

    # the label pictures' format is left to their content (`html.picture_bytes`): labels blended over the photo
    # are photographic (JPEG), a label map drawn without one (its photo unreadable) flat colour (PNG)
    for p in [p for p in sorted((twin / "semantics" / "masks_vs_labels").glob("*.png"))
              if ours(p) and picture(twin, p)]:
        sec.image(p, caption=f"{p.stem}: 2D masks (held-out view: not used by the fusion) | fused 3D labels rendered"
                  if p.stem in heldout else f"{p.stem}: 2D segmenter masks (input) | fused 3D labels rendered")
    maps = [p for p in sorted((twin / "semantics" / "label_maps").glob("*.png")) if ours(p) and picture(twin, p)]
    # the held-out views' maps (the fusion never saw them); a real capture's names do not say "heldout"
    held = [p for p in maps if "heldout" in p.stem or p.stem in heldout] or maps
    for p in held[:4]:
        sec.image(p, caption=f"{p.stem}: fused labels rendered"
                  + (" (held-out view: not used by the fusion)" if p.stem in heldout or "heldout" in p.stem else ""))


def _heldout_names(twin: Path) -> set[str]:
    """The capture's held-out view names (TWIN/poses/transforms.json), empty when it cannot be read."""
    from splattwin.capture import load_dataset

    tj = twin / "poses" / "transforms.json"
    try:
        return {f.name for f in load_dataset(tj, validate=False).heldout()} if tj.is_file() else set()
    except InputError:
        return set()


def _geometry_section(sec: Section, twin: Path, man, geo: dict | None) -> None:
    if man is None:
        sec.text("twin stage not run")
        return
    from splattwin.twin.manifest import missing_obstacle_boxes, missing_obstacle_boxes_note

    rows = []
    for o in man.objects:
        cov = "n/a" if o.silhouette_coverage is None else f"{o.silhouette_coverage:.0%}"
        problem = o.problem or ""
        if o.obstacle_only:   # unusable, yet in every collision export and the robot's world as its box
            problem = (f"{problem}; kept as a static obstacle box (an estimate of its extent) that the robot "
                       f"avoids: it cannot be picked or placed on").lstrip("; ")
        rows.append([o.name, "no: obstacle-only box (estimate)" if o.obstacle_only else o.usable,
                     "1 box" if o.obstacle_only else len(o.convex_parts), o.mass if o.mass is not None else "n/a",
                     length_text(o.bbox_extent, man.frame.scaled), cov, problem])
    sec.table(["object", "usable", "convex parts", "mass (kg)" if man.frame.scaled else "mass (nominal)", "box",
               "masks covered", "problem"], rows)
    missing = missing_obstacle_boxes(man)
    if missing:
        sec.text(f"WARNING: {missing_obstacle_boxes_note(missing, twin.resolve().name)}.")
    if any(o.silhouette_coverage is not None for o in man.objects):
        sec.text("masks covered: the share of each object's 2D masks that its cleaned splats, rendered alone, "
                 "cover (median over views); a fragment of an object covers little of them.")
    if not man.frame.scaled:
        sec.text("lengths in SfM units: the twin is unscaled (no metric scale), so they are not metres.")
    b = man.background
    if b.table_default:
        x0, x1, y0, y1 = b.table_extent
        sec.text(f"WARNING: the table is assumed ({b.table_default}); the twin's table is"
                 f" x {length_text([x0, x1], man.frame.scaled, ' .. ')}, y "
                 f"{length_text([y0, y1], man.frame.scaled, ' .. ')}, top at z = "
                 f"{length_text([b.table_height], man.frame.scaled)}: check it before relying on it.")
    carve = (man.timings or {}).get("geometry.carve")
    sec.text("meshes: alpha shapes of the objects' half-opaque splats (solid down to the table when resting on it)"
             + (f", carved where a capture camera sees through them to the splats' rendered surface ({carve:.2f} s)"
                if carve is not None else " (not carved: no capture cameras, or carving off)") + ".")
    dc = (man.config or {}).get("depth_carving")
    if isinstance(dc, dict) and dc.get("used") and isinstance(dc.get("objects"), dict):
        def share(v: dict) -> str:
            d, n = v.get("dropped"), v.get("points")
            ok = all(isinstance(x, int) and not isinstance(x, bool) for x in (d, n)) and n > 0
            return f"{d} of {n} points ({100 * d / n:.1f} %, {plural(v.get('views') or 0, 'depth view')})" if ok \
                else f"{d} of {n} points ({v.get('views')} depth views)"

        tol, noise, erode = dc.get("tolerance"), dc.get("noise_1m"), dc.get("erode_px")
        rule = (f" (more than {tol * 1000:.1f} mm + {noise * 1000:.1f} mm × z² in front of the measured depth z "
                f"in m, inside the object's mask eroded by {erode} px)"
                if all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (tol, noise)) else "")
        parts = [f"{k} {share(v)}" for k, v in dc["objects"].items() if isinstance(v, dict)]
        # "cardboard_box 1779 of 59493 points" alone did not say what happened to those points
        sec.text("carved against the capture's measured depth too: the points (splat centres and ellipsoid "
                 f"samples) a depth camera saw through were dropped as free space{rule}: "
                 + (", ".join(parts) or "no object had depth views") + ".")
    elif isinstance(dc, dict) and isinstance(dc.get("skipped"), str):
        sec.text(f"not carved against measured depth: {dc['skipped']}.")
    if geo:
        gt = (man.config or {}).get("ground_truth") if man is not None else None
        if isinstance(gt, dict) and gt.get("alignment"):
            sec.text(f"{gt['alignment'][:1].upper()}{gt['alignment'][1:]}.")
        sec.table(["object", "Chamfer (m)", "precision", "recall", "F1 @5 mm"],
                  [[k, v.get("chamfer"), v.get("precision"), v.get("recall"), v.get("f1")] for k, v in geo.items()])
    tj = twin / "poses" / "transforms.json"
    ds = None
    if tj.is_file():
        from splattwin.capture import load_dataset

        try:
            ds = load_dataset(tj, validate=False)
        except InputError as e:
            sec.text(f"no camera views of the collision geometry: {e}")
    if ds is not None:
        frames = ds.frames[:: max(1, len(ds.frames) // 3)][:3]
        obst = [o.name for o in man.objects if o.obstacle_only]
        held = {f.name for f in ds.heldout()}
        caption = "photo | collision geometry (convex parts) from its camera, colours as in the key" + (
            f"; translucent red: the static obstacle {'box' if len(obst) == 1 else 'boxes'} of unusable "
            f"{'object' if len(obst) == 1 else 'objects'} {', '.join(obst)} (an estimate)" if obst else "")
        for name, img in _collision_views(twin, frames):
            sec.image(img, caption=f"{name}{' (held-out view)' if name in held else ''}: {caption}", photo=True)
    if man.exports:
        sec.table(["export", "path"], [[k, v] for k, v in man.exports.items()])


def _robot_section(sec: Section, twin: Path, robot: dict | None, stale: str | None = None, man=None) -> None:
    if stale:
        sec.text(f"no robot results shown: {stale}.")
        return
    if not robot and man is not None and not man.frame.scaled:
        # "run splattwin plan" could never work here: plan refuses a twin in SfM units (mjcf.check_scaled)
        sec.text("no robot plan: the twin is unscaled (lengths in SfM units, not metres), and a robot cannot plan "
                 "in SfM units, so `splattwin plan` and `build --task` refuse it. Rebuild it with a metric scale "
                 "(--known-length camera_height=M or baseline@IMG_A,IMG_B=M, --marker-size M, metric known poses or "
                 "metric depth images) to plan a task.")
        return
    if not robot:
        sec.text("no robot task run (splattwin plan TWIN, or build with --task)")
        return
    if "error" in robot:
        sec.text(f"the task could not run on this twin: {robot['error']}")
        return
    nom = robot["nominal"]
    moved = (robot.get("settle") or {}).get("moved") or []
    overall = ("SUCCESS in simulation, but NOT a validation of the twin (objects moved before the robot acted)"
               if nom["success"] and moved else "SUCCESS" if nom["success"] else "FAILURE")
    sec.text(f"task: {robot['task']}; planner {robot['planner']}; overall: {overall}.")
    rows = []
    for s in nom["steps"]:
        rows.append([s["index"], s["pick"], s["goal"], s["grasped"], s["placed"], s["at_rest"],
                     s["robot_collisions"] + s["object_collisions"], s["success"], s.get("failure") or ""])
    planned = _task_steps(nom)
    ran = {s["index"] for s in nom["steps"]}
    skipped = [t for t in planned or [] if t["index"] not in ran]
    rows += [[t["index"], t["pick"], t["goal"], "-", "-", "-", "-", "-", "not attempted"] for t in skipped]
    sec.table(["step", "pick", "goal", "grasped", "placed", "at rest", "collisions", "success", "note"], rows)
    if nom["steps"] and not nom["steps"][-1]["success"]:
        # the executor stops at the first failed step (`Executor.run`): a table ending there read as the task
        failed = nom["steps"][-1]["index"]
        if planned is None:   # results.json of an earlier splattwin: no step list recorded
            sec.text(f"the run stopped at the failed step {failed}: the task's later steps, if any, were not "
                     f"attempted.")
        elif skipped:
            sec.text(f"the run stopped at the failed step {failed} of {len(planned)}: {_steps_text(skipped)} "
                     f"not attempted.")
        else:
            sec.text(f"the run stopped at the failed step {failed}, the task's last.")
    tr = robot.get("trials")
    if tr:
        # what was perturbed and what the interval is of: "3/3 trials at σ = 5.0 mm (95 % CI 0.44-1.00)"
        # left both to be guessed (the yaw error was not said at all)
        yaw = tr.get("sigma_yaw")
        yaw = (f" and its yaw by σ = {np.degrees(yaw):.1f}°"
               if isinstance(yaw, (int, float)) and not isinstance(yaw, bool) else "")
        sec.text(f"robustness: {tr['successes']}/{tr['trials']} trials succeeded, each with every object's x and y "
                 f"position perturbed by σ = {tr['sigma'] * 1000:.1f} mm per axis{yaw} (the robot plans with the "
                 f"twin's poses); success rate {tr['successes'] / max(tr['trials'], 1):.2f}, 95 % confidence interval "
                 f"{tr['ci95'][0]:.2f}–{tr['ci95'][1]:.2f}; {plural(tr['collisions'], 'collision')} in all trials.")
    _real_arm_rows(sec, twin, robot)
    ov = physics_overview(twin)
    if ov is not None:   # shown here only (the task-in-motion section's video refers to it)
        sec.image(ov, caption="execution in MuJoCo", photo=True)
    for n in robot.get("notes", []):
        if not (isinstance(robot.get("real_robot"), dict) and robot["real_robot"].get("reason")
                and str(robot["real_robot"]["reason"]) in str(n)):   # the table above says it
            sec.text(f"note: {n}")


def _task_steps(nominal: dict) -> list[dict] | None:
    """results.json `nominal.task_steps` (every step of the task: `robot.execute.task_step_list`), None when
    it is not recorded (an earlier splattwin) or not a list of {index: int, pick, goal}."""
    steps = nominal.get("task_steps")
    ok = isinstance(steps, list) and all(
        isinstance(t, dict) and isinstance(t.get("index"), int) and not isinstance(t.get("index"), bool)
        and isinstance(t.get("pick"), str) and isinstance(t.get("goal"), str) for t in steps)
    return steps if ok else None


def _steps_text(steps: list[dict]) -> str:
    """'step 3 (mug on tray) was' / 'steps 3-4 (mug on tray, cup in bin) were': the steps not attempted."""
    idx = [t["index"] for t in steps]
    run = len(idx) > 1 and idx == list(range(idx[0], idx[-1] + 1))
    span = f"{idx[0]}-{idx[-1]}" if run else ", ".join(map(str, idx))
    what = ", ".join(f"{t['pick']} {t.get('place') if t.get('place') in ('on', 'in') else 'to'} {t['goal']}"
                     for t in steps[:8]) + (", ..." if len(steps) > 8 else "")
    return f"step {span} ({what}) was" if len(steps) == 1 else f"steps {span} ({what}) were"


def physics_overview(twin: Path) -> Path | None:
    """The robot run's MuJoCo frames in one picture (TWIN/robot/frames/overview.png; robot/overview.png of an
    older run), None when the run rendered none (no offscreen GL context, --no-render: its notes say)."""
    for p in (twin / "robot" / "overview.png", twin / "robot" / "frames" / "overview.png"):
        if picture(twin, p):
            return p
    return None


def _real_arm_rows(sec: Section, twin: Path, robot: dict) -> None:
    """What the run gives a real arm (robot/results.json, program.json): whether the files were written
    and why not, the program's phases, the exported joint names and base frame, the base pose and its
    file, the named robot's limit check, the servos' tracking error and the start check."""
    real = robot.get("real_robot") if isinstance(robot.get("real_robot"), dict) else {}
    rows = []
    if real.get("written"):
        rows.append(["real-arm files", "written: robot/program.json + program/, trajectory.*, gripper.ros2.yaml"])
        prog = _json(twin / "robot" / "program.json")
        phases = prog.get("phases") if isinstance(prog, dict) else None
        if isinstance(phases, list):
            kinds = [str(p.get("kind")) for p in phases if isinstance(p, dict)]
            rows.append(["program.json phases", f"{len(kinds)}: {kinds.count('arm')} arm, "
                         f"{kinds.count('gripper')} gripper (blocking), run in order"])
    elif real:
        reason = str(real.get("reason"))
        for st in (robot.get("nominal") or {}).get("steps") or []:
            why = st.get("failure") if isinstance(st, dict) else None
            if isinstance(why, str) and len(why) > 40 and why in reason:
                # the step table above has the failure word for word: 400 characters twice in a row
                reason = reason.replace(why, f"see step {st.get('index')}'s note above")
        rows.append(["real-arm files", f"NOT written: {reason}"])
    jn = robot.get("joint_names")
    if isinstance(jn, dict) and jn.get("exported"):
        ex = [str(n) for n in jn["exported"]]
        rows.append(["exported joint names", f"{ex[0]} .. {ex[-1]}" if len(ex) > 2 else ", ".join(ex)])
    if robot.get("base_frame"):
        rows.append(["base frame", robot["base_frame"]])
    bp = robot.get("base_pose")
    if isinstance(bp, dict):
        rows.append(["base pose in the twin frame", f"x {bp.get('x')}, y {bp.get('y')}, z {bp.get('z')} m, "
                     f"yaw {bp.get('yaw')} rad (robot/base_transform.yaml)"])
    if real.get("limit_violations"):
        rows.append(["robot limits", f"exceeded: {'; '.join(map(str, real['limit_violations']))[:600]}"])
    elif real.get("limits_checked"):
        rows.append(["robot limits", f"checked, inside ({real['limits_checked']})"])
    tr = robot.get("tracking")
    if isinstance(tr, dict) and tr.get("tcp_max_m") is not None:
        rows.append(["tracking error (physics vs commanded)",
                     f"TCP max {tr['tcp_max_m'] * 1000:.2f} mm, median {tr.get('tcp_median_m', 0) * 1000:.2f} mm; "
                     f"joints max {tr.get('joint_max_rad')} rad"])
    st = robot.get("settle")
    if isinstance(st, dict) and isinstance(st.get("objects"), dict) and st["objects"]:
        worst = max(st["objects"], key=lambda o: st["objects"][o].get("moved_m", 0.0))
        w = st["objects"][worst]
        verdict = (f"FAILED: {', '.join(st.get('moved') or [])} moved" if st.get("moved") else "passed")
        rows.append(["start check (objects at rest)",
                     f"{verdict}; largest move {worst} {w.get('moved_m', 0) * 100:.1f} cm, "
                     f"{w.get('turned_deg', 0):.1f} deg in {st.get('time_s')} s before the robot acted "
                     f"(limits {st.get('threshold_m', 0) * 100:g} cm, {st.get('threshold_deg')} deg)"])
    if rows:
        sec.table(["for the real arm", "value"], rows)
