"""Capture: cameras, image/video/dataset readers and writers (nerfstudio, COLMAP, 3DGS cameras.json)."""

from splattwin.capture.camera import Camera, invert_se3, look_at, opencv_from_opengl, opengl_from_opencv

__all__ = ["Camera", "invert_se3", "look_at", "opencv_from_opengl", "opengl_from_opencv"]
