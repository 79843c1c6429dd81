"""A parameter grid over a twin: semantic fusion (κ, refinement rounds, ...), geometry cleaning options
and the trials' pose error σ; every cell validated by Monte-Carlo trials; one table of results.

    cells = product of the values of every parameter (params.py maps each onto its options object)

Work is split by what a parameter changes, and each piece is one task on the executor:

    fusion task   per distinct fusion setting      OUT/fusion/<id>/   labels, fusion.json, metrics
    twin task     per distinct (fusion, geometry)  OUT/twins/<id>/    a full twin folder + metrics
    trial tasks   per cell, one per trial          OUT/cells/<id>/trials/<i>.json

A fusion task starts the twin tasks that use it as soon as it finishes, and a twin task its cells'
trials (`Executor.run` chains them), so the cluster stays busy. Without fusion parameters the twin's own
labels are re-used; without fusion or geometry parameters every cell runs on the twin itself.
Each task writes its outputs atomically and a `result.json` with its key (inputs by content + options)
last; a re-run (or a retried task) skips what is finished with the same key.

Outputs: OUT/sweep.json (grid, cells, summary), OUT/sweep.csv (one row per cell), OUT/sweep.png (success
rate with its 95 % interval per cell), and the same table printed.
"""

from __future__ import annotations

import csv
import hashlib
import io as _io
import itertools
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from splattwin import io
from splattwin.hashing import sha256_file
from splattwin.cluster import params as P
from splattwin.executor import Executor, Job, Outcome, Resources, limit_threads
from splattwin.errors import InputError, short_repr
from splattwin.limits import MAX_RECORD_BYTES

log = logging.getLogger(__name__)

RESULT = "result.json"


@dataclass
class SweepSpec:
    """A sweep over the twin folder `twin`.

    grid: canonical parameter name ("fusion.kappa", "geometry.min_opacity", "trials.sigma", ...) -> values.
    trial: the trials' base spec (task, robot, base pose, seed, planner; sigma from the grid or its own).
    trials: trials per cell. masks: 2D masks for fusion cells and for the silhouette coverage of the
    cells' twins' objects (default: those the twin was built with, when it carries them). scene: embedded-scene folder with ground truth (default TWIN/scene when present).
    """

    twin: Path
    grid: dict[str, list]
    trial: Any                       # splattwin.robot.trials.TrialSpec
    trials: int = 20
    masks: Path | None = None
    scene: Path | None = None

    def cells(self) -> list[dict[str, Any]]:
        names = list(self.grid)
        return [dict(zip(names, vals)) for vals in itertools.product(*(self.grid[n] for n in names))]


# -- keys and small helpers --------------------------------------------------------------------------------
def digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def finished(folder: Path, key: dict) -> dict | None:
    """The folder's result.json when it was written for `key`, else None."""

    try:
        d = io.read_json(folder / RESULT, max_bytes=MAX_RECORD_BYTES)
    except (OSError, InputError):   # missing, too large or corrupt: the cell runs again
        return None
    return d if isinstance(d, dict) and d.get("key") == json.loads(json.dumps(key, default=str)) else None


def _twin_file(twin: Path, rel: str | None, what: str) -> Path:
    """A file the manifest names, relative to the twin folder (and inside it) or absolute."""
    if not rel:
        raise InputError(f"the twin records no {what} (fusion and geometry cells start from a twin built by "
                         f"`splattwin build` or `demo`)", twin / "twin.json")
    p = Path(rel)
    if not p.is_absolute():
        p = (twin / p).resolve()
        if not p.is_relative_to(twin.resolve()):
            raise InputError(f"the {what} path {rel!r} leaves the twin folder", twin / "twin.json")
    if not p.is_file():
        raise InputError(f"the twin's {what} is missing", p)
    return p


# -- masks and ground truth of the base twin ---------------------------------------------------------------
def resolve_scene(twin: Path, scene: Path | None) -> Path | None:
    if scene is not None:
        if not (Path(scene) / "scene.json").is_file():
            raise InputError("not an embedded-scene folder (no scene.json)", scene)
        return Path(scene)
    return twin / "scene" if (twin / "scene" / "scene.json").is_file() else None


def sweep_masks(twin: Path, manifest, masks: Path | None, scene: Path | None, dataset):
    """The 2D masks the fusion cells lift: --masks, else the twin's saved open-vocabulary masks
    (semantics/masks2d), else the embedded scene's simulated segmenter (training views only)."""
    from splattwin.semantics.masks import load_masks, scene_masks

    objects = {o.name: o.label for o in manifest.objects}
    if masks is not None:
        if not Path(masks).exists():
            raise InputError("masks not found", masks)
        return load_masks(masks, objects=objects)
    if (twin / "semantics" / "masks2d").is_dir():
        return load_masks(twin / "semantics" / "masks2d", objects=objects)
    if scene is not None:
        ms = scene_masks(scene, kind="noisy")
        train = {f.name for f in dataset.train()}
        for d in (ms.masks, ms.scores, ms.sizes):
            for view in [v for v in d if v not in train]:
                del d[view]
        return ms
    recorded = ((manifest.config.get("build") or {}).get("semantics") or {}).get("masks")
    hint = (f" (twin.json records {short_repr(recorded)}, which sweep does not follow: a twin may come from "
            f"someone else, so only paths inside it are used)") if isinstance(recorded, str) else ""
    raise InputError(f"fusion parameters need the 2D masks the twin was built from: pass --masks DIR{hint}", twin)


# -- tasks (run in workers) -------------------------------------------------------------------------------
def fusion_task(folder: str, key: dict, splats: str, cameras: str, masks: str, options: dict, cpus: float) -> dict:
    """Semantic fusion with one FusionOptions setting into `folder`; metrics in result.json."""
    done = finished(Path(folder), key)
    if done is not None:
        return done
    limit_threads(cpus)
    from splattwin.capture import load_dataset
    from splattwin.semantics.lift import fuse_to_dir, views_for
    from splattwin.semantics.masks import load_masks
    from splattwin.semantics.metrics import ghost_index, projection_consistency
    from splattwin.semantics.options import FusionOptions
    from splattwin.splat.config import filter_beside
    from splattwin.splat.gaussians import Gaussians

    out = Path(folder)
    t0 = time.perf_counter()
    g = Gaussians.load_ply(splats)
    ds = load_dataset(cameras)
    ms = load_masks(masks)
    res = fuse_to_dir(g, ds, ms, out, FusionOptions(**options), progress=False, raster=filter_beside(splats))
    io.write_json(out / "objects.json", [[res.names[k], int(k), (ms.prompts or {}).get(k, res.names[k].replace("_", " "))]
                                         for k in res.label_ids])
    meta = io.read_json(out / "fusion.json", max_bytes=MAX_RECORD_BYTES)
    views = views_for(ds.train() or ds.frames, ms)
    result = {"key": key, "labels": "labels.npy", "objects": "objects.json",
              "consistency": projection_consistency(g.means, res.labels, views, ms),
              "ghost_index": ghost_index(res), "miou_heldout": meta.get("miou_heldout"),
              "miou_train": meta.get("miou_train"), "labelled": int((res.labels > 0).sum()),
              "wall_s": time.perf_counter() - t0}
    io.write_json(out / RESULT, result)
    return result


def twin_task(folder: str, key: dict, base_twin: str, labels: str, objects: list, geometry: dict, scene: str | None,
              trial_spec, cpus: float, fusion: dict | None = None, masks: str | None = None) -> dict:
    """A twin folder from the base twin's splats, `labels` and one GeometryOptions setting; its metrics
    (usable objects, F1 against the scene's ground truth when there is one) and whether the task can run
    on it, in result.json. masks: the sweep's copy of the 2D masks (objects' silhouette coverage, as
    `build` measures it), or None."""
    out = Path(folder)
    done = finished(out, key)
    if done is not None:
        return done
    limit_threads(cpus)
    from splattwin.geometry.options import GeometryOptions
    from splattwin.options import from_dict
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.build import build_twin
    from splattwin.twin.manifest import Manifest

    t0 = time.perf_counter()
    base = Path(base_twin)
    bman = Manifest.load(base)
    if out.exists():   # a stale twin of another key (the base twin changed): start clean
        shutil.rmtree(out)
    g = Gaussians.load_ply(_twin_file(base, bman.splats, "splat file"))
    lab = _labels(Path(labels), len(g))
    cameras = _twin_file(base, bman.cameras, "cameras file") if bman.cameras else None
    ms = None
    if masks is not None:
        from splattwin.semantics.masks import load_masks

        ms = load_masks(masks)
    man = build_twin(g, lab, [tuple(o) for o in objects], out, frame=bman.frame, cameras_path=cameras,
                     options=from_dict(GeometryOptions, geometry), progress=False, masks=ms)
    if "target_frame" in bman.config:   # a scene fact the task needs (its goal region)
        man.config["target_frame"] = bman.config["target_frame"]
    # the resolved config of this twin: the base twin's, with this cell's geometry (and fusion) options
    build = json.loads(json.dumps(bman.config.get("build") or {}))
    build["geometry"] = geometry
    if fusion is not None:
        build.setdefault("semantics", {})["fusion"] = fusion
    man.config["build"] = build
    man.config["sweep"] = {"base_twin": str(base.resolve()), "labels": labels}
    man.save(out)
    result = {"key": key, "objects_usable": sum(1 for o in man.objects if o.usable), "objects": len(man.objects),
              "problems": {o.name: o.problem for o in man.objects if not o.usable},
              "f1": fidelity(out, man, Path(scene)) if scene else {}, "task_error": None}
    try:
        _check_task(out, man, trial_spec)
    except InputError as e:
        result["task_error"] = str(e)
    result["wall_s"] = time.perf_counter() - t0
    io.write_json(out / RESULT, result)
    return result


def _labels(path: Path, n: int) -> np.ndarray:
    """The per-Gaussian labels (.npy) of a twin, checked: never a pickle, one integer label per Gaussian in
    [0, MAX_LABEL], bounded by the file and that count before it is read. InputError naming the file."""
    from splattwin.limits import load_npy
    from splattwin.twin.manifest import MAX_LABEL

    lab = load_npy(path, "label array", max_bytes=8 * n + 1024)
    if lab.shape != (n,) or lab.dtype.kind not in "iu":
        raise InputError(f"label array must hold {n} integer labels (one per Gaussian), got {lab.dtype} "
                         f"{tuple(lab.shape)}", path)
    if n and (lab.min() < 0 or lab.max() > MAX_LABEL):
        raise InputError(f"labels must be in [0, {MAX_LABEL}], got {lab.min()} to {lab.max()}", path)
    return lab


def _check_task(twin: Path, man, spec) -> None:
    from splattwin.robot.task import load_task, validate_task

    task = load_task(spec.task_path, man)
    validate_task(task, man, twin, spec.base.matrix(), robot=spec.robot_model())


def fidelity(twin: Path, man, scene: Path, threshold: float = 0.005) -> dict[str, float]:
    """F1 @ threshold (m) of each usable object's visual mesh against the scene's ground-truth mesh,
    both sampled every 2 mm (as the build's geometry_metrics.json)."""
    from splattwin.geometry.metrics import fidelity as fid, sample_surface
    from splattwin.meshio import load_mesh

    out = {}
    for o in man.objects:
        gt = scene / "meshes" / f"{o.name}.ply"
        if not o.usable or not o.visual_mesh or not gt.is_file():
            continue
        mesh = load_mesh(twin / o.visual_mesh, f"visual mesh of {o.name!r}")   # checked: a received twin
        mesh.apply_transform(o.pose)
        f = fid(sample_surface(mesh, spacing=0.002), sample_surface(load_mesh(gt, "ground-truth mesh"), spacing=0.002),
                threshold=threshold)
        out[o.name] = float(f.f1)
    return out


# -- the driver ----------------------------------------------------------------------------------------------
def base_options(twin: Path, man) -> tuple[Any, Any]:
    """(FusionOptions, GeometryOptions) the twin was built with: its resolved config in twin.json
    (`config.build.semantics.fusion`, `config.build.geometry`, as `splattwin build` records it), else the
    defaults (a twin built by the stage commands records none). An entry that is not a valid option is an
    InputError naming twin.json."""
    from splattwin.geometry.options import GeometryOptions
    from splattwin.options import from_dict
    from splattwin.semantics.options import FusionOptions

    build = man.config.get("build") or {}
    where = twin / "twin.json"
    if not isinstance(build, dict):
        raise InputError("config.build must be a mapping (the resolved build options)", where)
    fusion = (build.get("semantics") or {}).get("fusion") or {}
    return from_dict(FusionOptions, fusion, where), from_dict(GeometryOptions, build.get("geometry") or {}, where)


def trial_options(twin: Path, man):
    """The robot stage's options the twin was built with (`config.build.robot`: task, base pose, planner,
    seed, ...), else the defaults: the base of a sweep's trials (flags override them)."""
    from splattwin.options import from_dict
    from splattwin.robot.options import RobotOptions

    robot = (man.config.get("build") or {}).get("robot") or {}
    if not isinstance(robot, dict):
        raise InputError("config.build.robot must be a mapping (the resolved robot options)", twin / "twin.json")
    robot = {k: v for k, v in robot.items() if k != "cluster"}   # where the build's trials ran: not the sweep's
    return from_dict(RobotOptions, _recorded_paths_inside(twin, robot), twin / "twin.json")


def _recorded_paths_inside(twin: Path, robot: dict) -> dict:
    """`robot` without the file options (task, robot MJCF, record folder, camera YAML) whose recorded path
    is outside the twin folder. A received twin.json is untrusted: its recorded paths must not make the
    sweep read a task or an MJCF (with its includes) from elsewhere, nor write a recording there; the user
    gives those on the command line. A path inside the twin folder (absolute, or relative to it) is kept."""
    import dataclasses

    from splattwin.cluster.cli import SWEEP_ROBOT_FLAGS
    from splattwin.paths import is_inside
    from splattwin.robot.options import RobotOptions

    files = {f.name for f in dataclasses.fields(RobotOptions)
             if f.metadata.get("path") or "Path" in str(f.type)} | {"record_camera"}
    out = dict(robot)
    for k in sorted(files & set(robot)):
        v = robot[k]
        if v is None or v == "default" or (k == "record_camera" and isinstance(v, str) and v.startswith("capture:")):
            continue
        p = Path(v) if isinstance(v, str) and v and "\x00" not in v else None
        if k == "record_camera" and p is not None and p.suffix.lower() not in (".yaml", ".yml"):  # an image name
            continue
        if p is not None and not p.is_absolute():
            p = twin / p
        if p is not None and is_inside(p, twin) and p.exists():
            out[k] = str(p)
            continue
        del out[k]
        hint = f"; give --{k.replace('_', '-')} on the command line" if k in SWEEP_ROBOT_FLAGS else ""
        log.warning("%s: ignoring the recorded %s %s: it is not a file inside the twin folder (a received twin's "
                    "paths are not followed)%s", twin / "twin.json", k, str(v)[:100], hint)
    return out


@dataclass
class _Plan:
    cells: list[dict] = field(default_factory=list)            # per cell: params, ids, folders
    fusion: dict[str, dict] = field(default_factory=dict)     # id -> {options, key, folder}
    twins: dict[str, dict] = field(default_factory=dict)      # id -> {fusion id, geometry, key, folder}


def _short(key: Any) -> str:
    return digest(key)[:10]


def plan_sweep(spec: SweepSpec, out: Path, fusion_base, geometry_base) -> tuple[_Plan, dict]:
    """Cells and their fusion/twin tasks (ids from their keys). Returns (plan, context for the tasks)."""
    from splattwin.capture import load_dataset
    from splattwin.options import to_dict
    from splattwin.twin.manifest import Manifest

    twin = spec.twin
    man = Manifest.load(twin)
    grid_targets = {P.canonical(n).split(".")[0] for n in spec.grid}
    need_fusion, need_twin = "fusion" in grid_targets, bool(grid_targets & {"fusion", "geometry"})
    ctx: dict[str, Any] = {}
    scene = resolve_scene(twin, spec.scene)
    ctx["scene"] = str(scene.resolve()) if scene else None
    if need_twin:
        ctx["splats"] = str(_twin_file(twin, man.splats, "splat file"))
        ctx["splats_sha"] = sha256_file(Path(ctx["splats"]))
    ctx["masks"] = ctx["masks_sha"] = None
    ms = None
    if need_fusion:
        cameras = _twin_file(twin, man.cameras, "cameras file")
        ctx["cameras"] = str(cameras)
        ms = sweep_masks(twin, man, spec.masks, scene, load_dataset(cameras))
    elif need_twin and man.cameras:
        # the cells' twins judge their objects as `build` does: by splat count and silhouette coverage
        try:
            ms = sweep_masks(twin, man, spec.masks, scene, load_dataset(_twin_file(twin, man.cameras, "cameras file")))
        except InputError as e:
            log.warning("the cells' twins are built without 2D masks (objects judged by their splat count alone, "
                        "not as the twin was): %s", e)
    if ms is not None:
        ms.save(out / "masks")
        ctx.update(masks=str((out / "masks").resolve()), masks_sha=sha256_file(out / "masks" / "masks.json"))
    if need_twin and not need_fusion:
        ctx["labels"] = str(_twin_file(twin, man.labels, "labels file"))
        ctx["labels_sha"] = sha256_file(Path(ctx["labels"]))
        ctx["objects"] = [[o.name, o.label, o.prompt] for o in man.objects]
    tr = spec.trial
    # what decides whether the task can run on a cell's twin (checked by its twin task)
    task_key = {"task": sha256_file(Path(tr.task_path)) if tr.task_path else "default", "base": asdict(tr.base),
                "robot": sha256_file(Path(tr.robot_mjcf)) if tr.robot_mjcf else "panda", "tcp_site": tr.tcp_site}
    cameras_sha = sha256_file(Path(ctx["cameras"])) if need_fusion else None
    plan = _Plan()
    for i, cell in enumerate(spec.cells()):
        parts = P.split(cell)
        c: dict[str, Any] = {"cell": i + 1, "params": cell, "fusion": None, "twin": None}
        if need_fusion:
            fopts = to_dict(P.apply(fusion_base, parts["fusion"]))
            fkey = {"splats": ctx["splats_sha"], "cameras": cameras_sha,
                    "masks": ctx["masks_sha"], "options": fopts}
            fid = _short(fkey)
            plan.fusion.setdefault(fid, {"options": fopts, "key": fkey, "folder": out / "fusion" / fid})
            c["fusion"] = fid
        if need_twin:
            gopts = to_dict(P.apply(geometry_base, parts["geometry"]))
            tkey = {"splats": ctx["splats_sha"], "labels": c["fusion"] or ctx["labels_sha"], "geometry": gopts,
                    "scene": ctx["scene"], "task": task_key, "masks": ctx["masks_sha"]}
            tid = _short(tkey)
            plan.twins.setdefault(tid, {"fusion": c["fusion"], "geometry": gopts, "key": tkey,
                                        "folder": out / "twins" / tid})
            c["twin"] = tid
        c["trial_params"] = parts["trials"]
        c["folder"] = out / "cells" / _short({"twin": c["twin"], "trials": parts["trials"], "params": cell})
        plan.cells.append(c)
    return plan, ctx


def cell_trials(cell: dict, spec) -> int:
    """How many trials a sweep cell runs: `spec.trials`, or one when the cell perturbs nothing (sigma 0 and no
    yaw error: every trial would be the same deterministic run). The jobs and the progress total both count
    with it (the total counted one trial for any sigma 0, so a cell with sigma 0 and a yaw error miscounted)."""
    tp = cell["trial_params"]
    sigma = tp.get("sigma", spec.trial.sigma)
    sigma_yaw = tp.get("sigma_yaw", spec.trial.sigma_yaw)
    return 1 if sigma == 0 and not sigma_yaw else spec.trials


def run_sweep(spec: SweepSpec, out: str | Path, executor: Executor, progress: bool = True,
              resume: bool = True) -> dict:
    """Run the sweep into `out` on `executor`; the summary dict (also written to OUT/sweep.json)."""
    from splattwin.robot.trials import load_finished, run_trial_job, summarize_trials, trial_jobs
    from splattwin.twin.manifest import Manifest

    out = Path(out).absolute()     # workers may run in another directory (or on another node)
    out.mkdir(parents=True, exist_ok=True)
    twin = Path(spec.twin).absolute()
    spec = replace(spec, twin=twin)
    if not (twin / "twin.json").is_file():
        from splattwin.twin.manifest import no_twin_yet

        raise InputError("not a twin folder (no twin.json)" + no_twin_yet(twin), twin)
    from splattwin.robot.options import MAX_TRIALS

    if not 1 <= spec.trials <= MAX_TRIALS:
        raise InputError(f"--trials must be in [1, {MAX_TRIALS}], got {spec.trials}")
    man = Manifest.load(twin)
    from splattwin.robot.task import load_task
    from splattwin.twin.mjcf import check_scaled

    # every cell's twin has this twin's frame: an unscaled one fails every cell's trials (after all the
    # fusion and geometry work), so it is refused now, as `plan` refuses it
    check_scaled(man, twin / "twin.json")
    try:
        load_task(spec.trial.task_path, man)       # a malformed task file fails now, not in every cell
        if not {P.canonical(n).split(".")[0] for n in spec.grid} & {"fusion", "geometry"}:
            _check_task(twin, man, spec.trial)     # every cell runs on this twin: it must take the task
    except InputError as e:
        if spec.trial.task_path is not None:
            raise
        raise InputError(f"no --task given, and the default task (the embedded demo scene's three steps) does not "
                         f"fit this twin ({e.problem}): give yours with --task TASK.yaml", twin / "twin.json") from None
    fusion_base, geometry_base = base_options(twin, man)
    if not resume:
        for sub in ("fusion", "twins", "cells"):
            shutil.rmtree(out / sub, ignore_errors=True)
    t0 = time.perf_counter()
    plan, ctx = plan_sweep(spec, out, fusion_base, geometry_base)
    cpus = 1.0
    fusion_res: dict[str, Outcome] = {}
    twin_res: dict[str, Outcome] = {}
    trial_res: dict[int, dict[int, dict]] = {c["cell"]: {} for c in plan.cells}
    specs: dict[int, tuple[list, list, int]] = {}

    def cell_twin_dir(c: dict) -> Path:
        return plan.twins[c["twin"]]["folder"] if c["twin"] else twin

    def trials_of(c: dict) -> list[Job]:
        tp = c["trial_params"]
        sigma = tp.get("sigma", spec.trial.sigma)
        sigma_yaw = tp.get("sigma_yaw", spec.trial.sigma_yaw)
        base = replace(spec.trial, twin_dir=str(cell_twin_dir(c)),
                       **{k: v for k, v in tp.items() if k not in ("sigma", "sigma_yaw")})
        n = cell_trials(c, spec)
        sp, paths = trial_jobs(base, n, sigma, c["folder"], sigma_yaw)
        specs[c["cell"]] = (sp, paths, n)
        jobs = []
        for i, (s, p) in enumerate(zip(sp, paths)):
            prev = load_finished(p, s) if resume else None
            if prev is not None:
                trial_res[c["cell"]][i] = prev
            else:
                jobs.append(Job(("trial", c["cell"], i), run_trial_job, (s, str(p)), Resources(cpus),
                                name=f"sweep-cell{c['cell']}-trial{i + 1}"))
        return jobs

    def twin_job(tid: str) -> Job:
        t = plan.twins[tid]
        if t["fusion"]:
            fdir = plan.fusion[t["fusion"]]["folder"]
            labels, objects = str(fdir / "labels.npy"), io.read_json(fdir / "objects.json", max_bytes=MAX_RECORD_BYTES)
        else:
            labels, objects = ctx["labels"], ctx["objects"]
        fusion = plan.fusion[t["fusion"]]["options"] if t["fusion"] else None
        return Job(("twin", tid), twin_task, (str(t["folder"]), t["key"], str(twin.resolve()), labels, objects,
                                             t["geometry"], ctx["scene"], spec.trial, cpus, fusion, ctx["masks"]),
                   Resources(cpus), name=f"sweep-twin-{tid}")

    def on_done(job: Job, o: Outcome):
        kind = job.key[0]
        if kind == "fusion":
            fusion_res[job.key[1]] = o
            if o.ok:
                return [twin_job(tid) for tid, t in plan.twins.items() if t["fusion"] == job.key[1]]
        elif kind == "twin":
            twin_res[job.key[1]] = o
            if o.ok and not o.value.get("task_error"):
                return [j for c in plan.cells if c["twin"] == job.key[1] for j in trials_of(c)]
        else:
            _, cell, i = job.key
            trial_res[cell][i] = o.value if o.ok else {"success": False, "collisions": 0, "plan_ms": [],
                                                       "steps": [], "trial_wall_s": 0.0, "error": f"worker: {o.error}"}
        return []

    if plan.fusion:
        first = [Job(("fusion", fid), fusion_task, (str(f["folder"]), f["key"], ctx["splats"], ctx["cameras"],
                                                   ctx["masks"], f["options"], cpus),
                     Resources(cpus), name=f"sweep-fusion-{fid}") for fid, f in plan.fusion.items()]
    elif plan.twins:
        first = [twin_job(tid) for tid in plan.twins]
    else:
        first = [j for c in plan.cells for j in trials_of(c)]
    n_trials = sum(cell_trials(c, spec) for c in plan.cells)
    total = len(plan.fusion) + len(plan.twins) + n_trials - sum(len(v) for v in trial_res.values())
    executor.run(first, on_done=on_done, progress=progress, description="sweep", total=max(total, len(first)))

    rows = []
    for c in plan.cells:
        row: dict[str, Any] = {"cell": c["cell"], **{k: c["params"][k] for k in spec.grid}, **dict.fromkeys(COLUMNS)}
        err = None
        fo = fusion_res.get(c["fusion"]) if c["fusion"] else None
        if fo is not None:
            if fo.ok:
                row.update({k: fo.value.get(k) for k in ("consistency", "ghost_index", "miou_heldout")})
            else:
                err = f"fusion: {fo.error}"
        to = twin_res.get(c["twin"]) if c["twin"] else None
        if to is not None:
            if to.ok:
                v = to.value
                row["objects_usable"] = f"{v['objects_usable']}/{v['objects']}"
                row["f1_min"] = min(v["f1"].values()) if v["f1"] else None
                err = v.get("task_error") and f"task: {v['task_error']}"
            else:
                err = f"geometry: {to.error}"
        elif c["twin"] and err is None:
            err = "not run (its fusion failed)"
        if c["cell"] in specs and not err:
            sp, _, n = specs[c["cell"]]
            done = [trial_res[c["cell"]][i] for i in sorted(trial_res[c["cell"]])]
            s = summarize_trials(done, n, sp[0].sigma, sp[0].sigma_yaw)
            errors = sorted({r["error"] for r in done if r.get("error")})
            row.update(trials=n, successes=s["successes"], success_rate=s["success_rate"], ci95_lo=s["ci95"][0],
                       ci95_hi=s["ci95"][1], collisions=s["collisions"])
            if errors:
                err = f"{len(errors)} trial error(s): {errors[0]}"
        row["twin"] = str(cell_twin_dir(c))
        row["error"] = err
        rows.append(row)
    summary = {"twin": str(twin.resolve()), "grid": spec.grid, "trials_per_cell": spec.trials,
               "task": spec.trial.task_path or "default (the paper's three steps)", "seed": spec.trial.seed,
               "sigma_definition": "trials.sigma: per-axis standard deviation (m) of each object's x and y position "
                                   "error; trials.sigma_yaw: yaw (rad), default sigma / 0.1 m",
               "executor": executor.describe(), "wall_s": time.perf_counter() - t0, "cells": rows}
    summary["outputs"] = {k: str(v) for k, v in write_outputs(out, summary).items()}
    io.write_json(out / "sweep.json", summary)
    return summary


# -- outputs ----------------------------------------------------------------------------------------------------
COLUMNS = ("consistency", "ghost_index", "miou_heldout", "objects_usable", "f1_min", "trials", "successes",
           "success_rate", "ci95_lo", "ci95_hi", "collisions", "error")


def columns(summary: dict) -> list[str]:
    cols = ["cell", *summary["grid"]]
    present = {k for r in summary["cells"] for k, v in r.items() if v is not None}
    return cols + [c for c in COLUMNS if c in present or c in ("trials", "successes", "success_rate")]


def write_outputs(out: Path, summary: dict) -> dict[str, Path]:
    cols = columns(summary)
    buf = _io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    for r in summary["cells"]:
        w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])
    paths = {"json": io.write_json(out / "sweep.json", summary), "csv": io.write_text(out / "sweep.csv", buf.getvalue())}
    try:
        paths["png"] = plot(summary, out / "sweep.png")
    except Exception as e:  # the picture is a convenience; the table is the result
        log.info("sweep plot not written: %s", e)
    return paths


def plot(summary: dict, path: Path) -> Path:
    """Success rate per cell with its Wilson 95 % interval (the cell's parameters under each bar)."""
    from matplotlib.figure import Figure

    rows = [r for r in summary["cells"] if r.get("success_rate") is not None]
    if not rows:
        raise ValueError("no cell ran trials")
    # a Figure of its own, not pyplot: the caller's backend and open figures stay as they are (a notebook's)
    fig = Figure(figsize=(max(5.0, 0.9 * len(rows) + 2), 3.6), dpi=110)
    ax = fig.subplots()
    x = np.arange(len(rows))
    rate = np.array([r["success_rate"] for r in rows])
    lo = rate - np.array([r["ci95_lo"] for r in rows])
    hi = np.array([r["ci95_hi"] for r in rows]) - rate
    ax.bar(x, rate, color="#4c78a8")
    ax.errorbar(x, rate, yerr=[lo, hi], fmt="none", ecolor="#1d2330", capsize=3)
    names = list(summary["grid"])
    ax.set_xticks(x, ["\n".join(f"{n.split('.')[-1]}={r[n]:g}" if isinstance(r[n], float) else f"{n.split('.')[-1]}={r[n]}"
                                for n in names) for r in rows], fontsize=7)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("task success rate")
    ax.set_title(f"{summary['trials_per_cell']} trials per cell, 95 % Wilson interval", fontsize=9)
    fig.tight_layout()
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def print_table(summary: dict, paths: dict | None = None) -> None:
    from splattwin.console import console
    from rich.table import Table

    cols = [c for c in columns(summary) if c != "error"]
    t = Table(title=f"sweep of {summary['twin']}  ({summary['executor']}, {summary['wall_s']:.0f} s)")
    for c in cols:
        t.add_column(c.split(".")[-1], overflow="fold")
    for r in summary["cells"]:
        t.add_row(*[_fmt(r.get(c)) for c in cols])
    con = console()
    con.print(t)
    for r in summary["cells"]:
        if r.get("error"):
            e = r["error"]
            con.print(f"[red]cell {r['cell']}[/]: {e if len(e) < 240 else e[:237] + '...'}")
    if paths:
        con.print("  ".join(f"{k}: {v}" for k, v in paths.items()))


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
