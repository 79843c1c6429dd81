"""Commands that run or show the twin in motion:

`splattwin plan TWIN [--task T.yaml --trials N --sigma S] [--record DIR]`: the robot stage (plan, validate in
MuJoCo, trials) and, with --record, every run as a LeRobot-layout episode (`playback.record`). The command
lives here, not in `robot/`, because recording renders the splats: the robot stage may not import playback
(docs/ARCHITECTURE.md, layering); its options are the robot stage's (`RobotOptions`, record fields included).

`splattwin render TWIN --camera CAM --out video.mp4`: the executed task, photoreal, from any camera.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from splattwin.options import add_command, add_options, add_progress_flag
from splattwin.robot.options import RobotOptions

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Add `plan` and `render` to the `splattwin` parser."""
    p = add_command(sub, "plan", run_plan)
    p.add_argument("twin", type=Path, help="twin folder (with twin.json)")
    add_options(p, RobotOptions)
    p.add_argument("--out", type=Path, default=None, help="output folder (default: TWIN/robot)")
    add_progress_flag(p)

    p = add_command(sub, "render", run_render)
    p.add_argument("twin", type=Path, help="twin folder (with twin.json and splats)")
    p.add_argument("--camera", default="capture:0",
                   help="a capture image name (e.g. heldout_000), 'capture:<index>', 'wrist' (eye-in-hand, "
                        "D435-like) or a camera YAML (see splattwin.playback.cameras); default capture:0")
    p.add_argument("--out", type=Path, required=True, help="MP4 to write")
    p.add_argument("--rollout", type=Path, default=None, help="rollout .npz (default TWIN/robot/rollout.npz)")
    p.add_argument("--fps", type=float, default=30.0, help="video frame rate (default 30)")
    p.add_argument("--width", type=int, default=None,
                   help="rescale the camera to this width (pixels; the wrist camera too, aspect kept)")
    p.add_argument("--base-pose", default=None,
                   help="robot base in the twin frame: x,y,z,yaw (m, rad); write --base-pose=-0.5,0,0,0 "
                        "(default: the one `splattwin plan` recorded in the results.json beside the rollout, "
                        "else in TWIN/robot/results.json, else -0.5,0,0,0)")
    p.add_argument("--no-robot", action="store_true", help="leave the robot out of the picture")
    p.add_argument("--no-fill", action="store_true", help="do not fill the table under moved objects")
    p.add_argument("--keep-view-dependence", action="store_true",
                   help="moved objects keep the capture's view-dependent colour (default: it fades out over "
                        "their first 5 cm of motion; see playback/scene.py)")
    p.add_argument("--no-relight", action="store_true",
                   help="keep every splat's trained colour (default: moved objects cast and receive shadows under "
                        "the light estimated from the twin's own shadows; see playback/relight.py)")
    add_progress_flag(p)


def run_plan(args: argparse.Namespace) -> int:
    """Plan a pick-and-place task on a twin and validate it in MuJoCo physics (Franka Panda).

    Plans the task against the twin (grasps, IK, OMPL paths, TOPP-RA timing), executes it in MuJoCo with
    the real gripper, reports per-step success and collisions, exports the joint trajectory (JSON, CSV,
    ROS 2 JointTrajectory YAML) and frames. With --record DIR every run (nominal, then each trial) is also
    written as a LeRobot-layout episode rendered from the twin's splats (wrist + scene camera). A twin that
    has a report (TWIN/report/index.html) gets it re-written with this run's results (--no-report: kept). Exit code
    0 when the task succeeded, 1 when it failed, 2 on bad input, when the trajectory leaves the limits of
    the robot named by --joint-names (fr3: the plan ran, results.json records it, no real-robot files) or
    when an object moved from its twin pose before the robot acted (floating: the run validates nothing)."""
    from splattwin.console import console

    from splattwin.errors import InputError
    from splattwin.lock import output_lock
    from splattwin.options import from_args
    from splattwin.paths import is_inside
    from splattwin.playback.record import record_result, recorder_for
    from splattwin.robot.outputs import print_summary
    from splattwin.robot.stage import RobotInputs, run

    opts = from_args(RobotOptions, args)
    opts.validate()
    out = args.out or args.twin / "robot"
    if not args.twin.is_dir():
        raise InputError("twin folder does not exist", args.twin)
    # everything the recording needs is checked before the physics runs
    recorder = recorder_for(args.twin, out, opts) if opts.record is not None else None
    # one writer per folder: the twin's lock when writing into it (splattwin.lock)
    with output_lock(args.twin if is_inside(out, args.twin) else out):
        t0 = time.perf_counter()
        res = run(RobotInputs(args.twin, out), opts, progress=args.progress)
        d = res.details
        print_summary(d["run"], d["trials"], d["paths"], d.get("real_robot"))
        if recorder is not None:
            info = record_result(recorder, opts.record, out, d, progress=args.progress)
            console().print(f"recorded {info['episodes']} episode(s) into {info['path']} "
                            f"({info['reused']} reused from a killed run; {info['fps']:g} fps, cameras "
                            + ", ".join(f"{k} {w}x{h}" for k, (w, h) in info["cameras"].items()) + ")")
        # what the layers above add to a plan (the report's refresh: `report.cli`), inside the same lock
        # with this run's seconds (the physics, the trials and the recording; not the report's refresh)
        after = getattr(args, "after_plan", None)
        if after is not None:
            after(args, out, seconds=time.perf_counter() - t0)
    if res.export_error:   # the plan ran, but no real-arm files: outside the named robot's limits
        # (`--joint-names fr3`) or the scene moved before the robot acted; the summary above said why
        console(stderr=True).print("error: no files for the real arm (the reason is above and in results.json "
                                   "real_robot)", markup=False, highlight=False)
        return 2
    ok = res.success and (d["trials"] is None or d["trials"]["successes"] == d["trials"]["trials"])
    if res.success and not ok:   # "overall: success" above, yet exit 1: say why
        t = d["trials"]
        console(stderr=True).print(f"exit 1: {t['trials'] - t['successes']} of {t['trials']} perturbed trials failed "
                                   "(listed above); the nominal run succeeded and its files for the real arm are "
                                   "written", markup=False, highlight=False)
    return 0 if ok else 1


def run_render(args: argparse.Namespace) -> int:
    """Render the executed task as a photoreal MP4 (moving splats + the robot) from any camera.

    Plays a rollout (TWIN/robot/rollout.npz, written by `splattwin plan`) on the twin's splats: objects
    move with the simulation, the Panda is drawn as Gaussians from its meshes, the table under picked
    objects is filled. Exit code 2 on bad input (no splats, camera below the table, ...)."""
    from splattwin.console import console

    from splattwin.errors import InputError
    from splattwin.playback.cameras import EyeInHand, resolve_camera
    from splattwin.playback.movie import render_rollout_video
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.robot import RobotSplats
    from splattwin.playback.scene import DynamicScene
    from splattwin.robot.rollout import Rollout
    if not 0 < args.fps <= 240:
        raise InputError(f"--fps must be in (0, 240], got {args.fps}")
    if args.width is not None and not 16 <= args.width <= 8192:
        raise InputError(f"--width must be in [16, 8192], got {args.width}")
    if args.out.suffix.lower() != ".mp4":
        raise InputError("--out must name an .mp4 file", args.out)
    _check_out(args.out)
    from splattwin.paths import own_file
    from splattwin.twin.manifest import Manifest

    rpath = args.rollout or args.twin / "robot" / "rollout.npz"
    if args.rollout is None:   # the twin's own files: a link out of it is named before the rollout is judged
        Manifest.load(args.twin)
        own_file(args.twin, rpath, "robot/rollout.npz")
    if not rpath.is_file():

        if args.rollout is None and not Manifest.load(args.twin).frame.scaled:
            # plan refuses a twin in SfM units, so "run plan first" could never work here
            raise InputError("no rollout to play: this twin is unscaled (SfM units), and `splattwin plan` only plans "
                             "in a metric twin; rebuild it with a metric scale (--known-length camera_height=M, "
                             "--marker-size M or metric known poses), then plan, or give --rollout", rpath)
        raise InputError("no rollout to play: run `splattwin plan TWIN` first (it writes robot/rollout.npz) or "
                         "give --rollout", rpath)
    if args.rollout is None:   # the twin's own rollout: it must have been made on the twin as it is now
        from splattwin.robot.outputs import stale_results

        why = stale_results(args.twin)
        if why is not None:
            raise InputError(f"robot/rollout.npz is not this twin's to play: {why}; or give --rollout", rpath)
    failed = _failed_run(_results_of(args))
    if failed is not None:   # said before the render (minutes), so the video is not taken for the task done
        console(stderr=True).print(f"note: this rollout is of a failed run ({failed}); the video shows it as "
                                   "physics played it", markup=False, highlight=False)
    scene = DynamicScene.load(args.twin, fill_holes=not args.no_fill, view_fade=not args.keep_view_dependence,
                              relight=not args.no_relight)
    camera = resolve_camera(args.camera, args.twin, width=args.width)
    rollout = Rollout.load(rpath)
    unknown = sorted(set(rollout.object_poses) - set(scene.objects))
    if unknown:
        console(stderr=True).print(f"note: rollout objects without splats stay unrendered: {', '.join(unknown)}")
    robot = None if args.no_robot else RobotSplats.panda(_base_pose(args).matrix())
    if isinstance(camera, EyeInHand) and robot is None:
        raise InputError("an eye-in-hand camera needs the robot (drop --no-robot)")
    info = render_rollout_video(PlaybackRenderer(scene, robot), rollout, camera, args.out, fps=args.fps,
                                robot=robot is not None, progress=args.progress)
    if scene.light is not None:
        lt = scene.light
        console().print(f"re-lit: light from the twin's shadows at azimuth {lt.azimuth_deg:.0f} deg, elevation "
                        f"{lt.elevation_deg:.0f} deg (twin frame), ambient share {lt.ambient:.2f}")
    elif not args.no_relight:
        why = "no clear cast shadow found on the twin's table" if scene.meshes else "the twin has no object meshes"
        console().print(f"not re-lit: {why} (splats keep their trained colour)")
    console().print(f"wrote {info['path']}: {info['frames']} frames {info['width']}x{info['height']} at "
                    f"{info['fps']:g} fps, median {info['render_ms_median']:.0f} ms per frame"
                    + (" (a failed run: see the note above)" if failed is not None else ""))
    return 0


def _check_out(out: Path) -> None:
    """InputError when the video cannot be written at `out`, checked before the render (minutes): a folder
    of that name (the final rename failed after the whole render), a parent that is a file or a folder that
    cannot be written ("internal error" at the first frame). Creates nothing: the writer makes the folders."""
    import os

    from splattwin.errors import InputError

    if out.is_dir():
        raise InputError("--out is a folder: name the .mp4 file to write", out)
    existing = out.absolute().parent
    while not existing.exists() and existing != existing.parent:   # the folder the writer will create under
        existing = existing.parent
    if not existing.is_dir():
        raise InputError("cannot create the folder of --out: a file is in the way", existing)
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError("cannot write the folder of --out (permission denied)", existing)


def _failed_run(results_json: Path | None, limit: int = 240) -> str | None:
    """Why the run of `results_json` failed, in a short sentence (its first failed step), or None when it
    succeeded or its results cannot say (none, unreadable: the render goes on, as before)."""
    from splattwin import io

    if results_json is None or not results_json.is_file():
        return None
    try:
        nominal = (io.read_record(results_json) or {}).get("nominal") or {}
        if not isinstance(nominal, dict) or nominal.get("success") is not False:
            return None
        bad = next((st for st in nominal.get("steps") or [] if isinstance(st, dict) and not st.get("success")), None)
    except (OSError, AttributeError):
        return None
    if bad is None:
        return "not every step ran"
    why = str(bad.get("failure") or "no reason recorded")
    why = why if len(why) <= limit else why[:limit - 3] + "..."
    return f"step {bad.get('index')} ({bad.get('pick')} -> {bad.get('goal')}) failed: {why}"


def _base_pose(args: argparse.Namespace):
    from splattwin.robot.world import BasePose

    if args.base_pose is not None:
        return BasePose.parse(args.base_pose)
    # where the robot stood in the run that made the rollout: its results.json beside it (`plan --out DIR`
    # writes both there); the twin's own results are another run's, whose base may differ
    return BasePose.recorded(_results_of(args) or args.twin / "robot" / "results.json")


def _results_of(args: argparse.Namespace) -> Path | None:
    """The results.json of the run whose rollout is played: TWIN/robot/ for the twin's own, the one beside
    --rollout (`plan --out DIR` writes both there) when there is one, else None."""
    if args.rollout is None:
        return args.twin / "robot" / "results.json"
    beside = args.rollout.parent / "results.json"
    return beside if beside.is_file() else None
