"""Capture: cameras, image/video/dataset readers and writers (nerfstudio, COLMAP, 3DGS cameras.json)."""

from splattwin.capture.camera import Camera, invert_se3, look_at, opencv_from_opengl, opengl_from_opencv
from splattwin.capture.dataset import Dataset, Frame, load_dataset, load_depth, load_image, load_mask, resize_nearest

__all__ = ["Camera", "Dataset", "Frame", "invert_se3", "load_dataset", "load_depth", "load_image", "load_mask", "resize_nearest",
           "look_at", "opencv_from_opengl", "opengl_from_opencv"]
