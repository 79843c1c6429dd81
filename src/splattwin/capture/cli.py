"""Sub-commands of the capture stage: `capture info`, `capture convert`, `capture frames`."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.options import add_options
from splattwin.frame_options import FrameOptions
from splattwin.errors import InputError

FORMATS = ("nerfstudio", "colmap", "cameras-json")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("capture", help="inspect, convert and extract capture datasets")
    csub = p.add_subparsers(dest="capture_command", metavar="ACTION", required=True)

    info = csub.add_parser("info", help="summarise a dataset (any supported layout)")
    info.add_argument("path", type=Path, help="transforms.json, COLMAP folder, cameras.json, BOP scene, TUM pose "
                      "list + intrinsics, image folder or video")
    info.add_argument("--max-frames", type=int, default=None,
                      help="video: number of frames to extract, the sharpest of as many equal windows (default 30)")
    info.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines (video)")
    info.set_defaults(func=_info)

    conv = csub.add_parser("convert", help="write a dataset's cameras in another format")
    conv.add_argument("path", type=Path, help="input dataset")
    conv.add_argument("out", type=Path, help="output file (transforms.json / cameras.json) or COLMAP sparse folder")
    conv.add_argument("--format", choices=FORMATS, required=True,
                      help="camera format to write: nerfstudio transforms.json, COLMAP text model, or cameras.json "
                           "(required, no default)")
    conv.set_defaults(func=_convert)

    fr = csub.add_parser("frames", help="extract sharp, evenly spaced frames from a video")
    fr.add_argument("video", type=Path, help="video file (.mp4 .mov .avi .mkv .webm .m4v)")
    fr.add_argument("out", type=Path, help="output folder for PNG frames")
    # the options `poses`/`build` take the frames with (`--max-frames`, `--min-change`): one default, one help
    add_options(fr, FrameOptions)
    fr.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    fr.set_defaults(func=_frames)


def _info(args: argparse.Namespace) -> int:
    import tempfile

    from splattwin.capture.dataset import load_dataset
    from splattwin.heldout import default_heldout

    # a video's frames are extracted into a temporary folder: `info` writes nothing beside the capture
    with tempfile.TemporaryDirectory(prefix="splattwin-info-") as tmp:
        ds = load_dataset(args.path, max_frames=args.max_frames, frames_dir=Path(tmp), progress=args.progress)
    sizes = sorted({(f.camera.width, f.camera.height) for f in ds.frames})
    size = f"{sizes[0][0]}x{sizes[0][1]}" if len(sizes) == 1 else f"{len(sizes)} image sizes"
    if ds.meta.get("split"):   # the capture's own split: poses/train/build keep it
        split = f"{len(ds.train())} train, {len(ds.heldout())} held-out: the capture's own split"
    else:   # no split of its own: the one poses/train/build will use (without --heldout* options)
        held, _, rule = default_heldout(len(ds.frames))
        split = f"{len(ds.frames) - len(held)} train, {len(held)} held-out by the default rule: {rule}"
    print(f"{args.path}: {ds.meta.get('format')} dataset, {len(ds.frames)} frames "
          f"({split}), {size}, "
          f"poses: {'yes' if ds.has_poses else 'no'}, points: {0 if ds.points_xyz is None else len(ds.points_xyz)}")
    return 0


def _convert(args: argparse.Namespace) -> int:
    import tempfile

    from splattwin.capture import cameras_json, colmap, nerfstudio
    from splattwin.capture.dataset import is_video, load_dataset

    # a video's frames go to a temporary folder, as for `info`: a video has no poses to convert anyway,
    # and nothing is written beside the capture
    with tempfile.TemporaryDirectory(prefix="splattwin-convert-") as tmp:
        ds = load_dataset(args.path, frames_dir=Path(tmp) if is_video(args.path) else None)
    if not ds.has_poses:
        raise InputError("dataset has no camera poses to convert (estimate them first: splattwin poses)", args.path)
    if args.format == "nerfstudio":
        out = args.out if args.out.suffix == ".json" else args.out / "transforms.json"
        nerfstudio.write(ds, out)
    elif args.format == "colmap":
        out = colmap.write_text(ds, args.out)
    else:
        out = args.out if args.out.suffix == ".json" else args.out / "cameras.json"
        cameras_json.write(ds, out)
    print(f"wrote {out}")
    return 0


def _frames(args: argparse.Namespace) -> int:
    from splattwin.capture.video import VIDEO_MAX_FRAMES, extract_frames
    from splattwin.options import from_args

    opts = from_args(FrameOptions, args)
    paths = extract_frames(args.video, args.out, max_frames=VIDEO_MAX_FRAMES if opts.max_frames is None
                           else opts.max_frames, min_change=opts.min_change, progress=args.progress)
    print(f"wrote {len(paths)} frames to {args.out}")
    return 0
