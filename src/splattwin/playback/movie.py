"""An executed task as a photoreal MP4 from one camera (the report embeds it; `splattwin render`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.playback.cameras import EyeInHand, check_camera
from splattwin.playback.episode import sample_indices
from splattwin.playback.compositor import PlaybackRenderer, rollout_state
from splattwin.playback.video import Mp4Writer


def render_rollout_video(renderer: PlaybackRenderer, rollout, camera: Camera | EyeInHand, out: str | Path,
                         fps: float = 30.0, robot: bool = True, progress: bool = True) -> dict:
    """Write the rollout seen from `camera` as an MP4 at `fps` (frame k = the rollout's state at
    t0 + k / fps). A world camera below the table is refused (InputError). Returns {path, frames, fps,
    render_ms_median, width, height}."""
    if isinstance(camera, Camera):
        check_camera(camera, renderer.scene.table_height)
    src = sample_indices(rollout.t, fps)
    ms = []
    from splattwin.progress import track

    it = track(range(len(src)), "rendering video", unit="frame", enabled=progress)
    size = None
    with Mp4Writer(out, fps) as w:
        for k in it:
            poses, rpose = rollout_state(rollout, int(src[k]))
            rp = rpose if robot else None
            cam = renderer.camera_for(camera, rpose)
            f = renderer.render(cam, poses, rp)
            ms.append(f.timings["layout_ms"] + f.timings["raster_ms"] + f.timings["backdrop_ms"])
            w.write(f.to_uint8())
            size = (cam.width, cam.height)
    return {"path": str(out), "frames": int(len(src)), "fps": float(fps),
            "render_ms_median": float(np.median(ms)) if ms else None, "width": size[0], "height": size[1]}
