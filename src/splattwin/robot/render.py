"""Offscreen frames of the execution (MuJoCo renderer, EGL/OSMesa), or a clear note when no GL exists.

MuJoCo picks its GL backend from MUJOCO_GL when it is first imported; `splattwin.runtime.configure()`
(called first by the CLI) sets it to EGL on a machine without a display unless the user chose one.
Camera: a free camera looking at the table centre from the front-left, above the robot's reach.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin import io


class FrameRecorder:
    """Renders labelled PNG frames into `out_dir` (frame_<k>_<label>.png). `available` is False (and
    `note` says why) when no offscreen OpenGL context can be made; `__call__` is then a no-op."""

    def __init__(self, out_dir: str | Path, model, width: int = 640, height: int = 480):
        self.out_dir = Path(out_dir)
        self.paths: list[Path] = []
        self.note = ""
        self._r = None
        try:
            import mujoco

            self._r = mujoco.Renderer(model, height, width)
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FREE
            cam.lookat[:] = [0.0, 0.0, 0.1]
            cam.distance = 1.7
            cam.azimuth = 210.0
            cam.elevation = -35.0
            self._cam = cam
        except Exception as e:  # no EGL/OSMesa/GLFW context on this machine
            self.note = (f"no offscreen OpenGL context ({type(e).__name__}: {str(e).splitlines()[0][:160]}); "
                         "frames not rendered. Set MUJOCO_GL=egl (libegl1, Mesa) or MUJOCO_GL=osmesa (libosmesa6).")
            self._r = None

    @property
    def available(self) -> bool:
        return self._r is not None

    def __call__(self, label: str, world) -> None:
        if self._r is None:
            return
        self._r.update_scene(world.data, camera=self._cam)
        img = np.asarray(self._r.render(), dtype=np.uint8)
        p = self.out_dir / f"frame_{len(self.paths):03d}_{label}.png"
        io.write_image(p, img)
        self.paths.append(p)

    def contact_sheet(self, cols: int = 4, scale: int = 2) -> Path | None:
        """All frames downscaled by `scale` in one grid image (frames/overview.png)."""
        if not self.paths:
            return None
        from PIL import Image

        imgs = [np.asarray(Image.open(p).convert("RGB"))[::scale, ::scale] for p in self.paths]
        h, w, _ = imgs[0].shape
        rows = (len(imgs) + cols - 1) // cols
        sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
        for i, im in enumerate(imgs):
            r, c = divmod(i, cols)
            sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
        return io.write_image(self.out_dir / "overview.png", sheet)

    def close(self) -> None:
        if self._r is not None:
            self._r.close()
            self._r = None
