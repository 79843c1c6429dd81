"""Options of the report (`splattwin report TWIN`): the photoreal video of the validated task. Light module."""

from __future__ import annotations

from dataclasses import dataclass

from splattwin.errors import InputError
from splattwin.options import option


@dataclass
class ReportOptions:
    """How the report shows the task in motion (`report.playback`)."""

    video_camera: str = option("auto", "camera of the task video: 'auto' (the first held-out capture camera, else "
                               "the first capture camera), a capture image name, 'capture:<index>', 'wrist' or a "
                               "camera YAML (as `splattwin render --camera`)")
    video_fps: float = option(10.0, "frame rate of the task video", unit="Hz")
    video_width: int = option(320, "width of the task video (world cameras are rescaled)", unit="px")
    video: bool = option(True, "render the photoreal task video (needs splats and robot/rollout.npz)")

    def validate(self) -> None:
        if not 0 < self.video_fps <= 60:
            raise InputError(f"--video-fps must be in (0, 60] Hz, got {self.video_fps}")
        if not 16 <= self.video_width <= 4096:
            raise InputError(f"--video-width must be in [16, 4096] pixels, got {self.video_width}")
