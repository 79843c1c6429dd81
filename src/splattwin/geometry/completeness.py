"""Completeness of an object's cleaned splats: how much of its 2D masks' silhouettes they cover.

A splat count cannot tell a small whole object from a fragment of a large one: the 2.5 cm cube of the
robot-style capture keeps 48 splats after cleaning and meshes at F1@5 mm 0.97, while a short training's
19 cm toy hammer kept a 35-splat fragment 7 cm from where the hammer stands. The masks can: render the
object's cleaned splats alone from each camera that has a mask of it (the rasterizer's alpha, as the
twin renders them), and compare that silhouette with the mask:

    recall    = |mask ∩ silhouette| / |mask|        (how much of what the photo shows the splats cover)
    precision = |silhouette ∩ mask| / |silhouette|  (how much of the splats lies on the object's mask)

each with a tolerance of `tol_px` pixels (the silhouette, resp. the mask, dilated by it: a half-pixel
offset of a 6-pixel cube is no gap), aggregated by the median over views. A fragment covers a small
share of its object's silhouettes (recall), a whole object most of them. Recall is the measure: a mask
shows the visible part of the object only (occluders cut it), and the splats rendered alone cover the
occluded part too, which lowers the precision of a whole object but never its recall.

Frames: cameras in the twin frame (the splats' frame), masks in the cameras' image pixels. Cameras are
used as ideal pinholes (the rasterizer's model; lens distortion moves silhouettes by a pixel or two at
the image border, within the tolerance at the coarse render size) and scaled so their longest side is
at most `max_side` pixels; masks are resampled to that size (nearest pixel centre).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians


@dataclass
class Coverage:
    """Silhouette coverage of one object: medians over `views` views (see the module docstring)."""

    recall: float
    precision: float
    views: int
    per_view: list = field(default_factory=list)  # [(recall, precision)] of each view used

    def to_dict(self) -> dict:
        return {"recall": self.recall, "precision": self.precision, "views": self.views}


def resample_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """bool [height, width]: `mask` [H,W] read at the centres of the pixels of an image `width` x `height`
    covering the same field (nearest pixel)."""
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    if (H, W) == (height, width):
        return mask
    rows = np.minimum(((np.arange(height) + 0.5) * H / height).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * W / width).astype(np.int64), W - 1)
    return mask[np.ix_(rows, cols)]


def silhouette(gaussians: "Gaussians", camera: "Camera", min_alpha: float = 0.5) -> np.ndarray:
    """bool [H,W]: where the splats, rendered alone, reach an accumulated alpha of `min_alpha`."""
    from splattwin.splat.rendering import render

    _, alpha = render(gaussians, camera, mode="ED", colors=np.zeros((len(gaussians), 1), np.float32))
    return alpha >= min_alpha


def view_coverage(sil: np.ndarray, mask: np.ndarray, tol_px: int = 1) -> tuple[float, float]:
    """(recall, precision) of a silhouette against a mask of the same size, each with `tol_px` pixels of
    tolerance (see the module docstring). An empty silhouette has recall 0 and precision 0."""
    from scipy.ndimage import binary_dilation

    sil, mask = np.asarray(sil, dtype=bool), np.asarray(mask, dtype=bool)
    grow = (lambda a: binary_dilation(a, iterations=tol_px)) if tol_px > 0 else (lambda a: a)
    n_mask, n_sil = int(mask.sum()), int(sil.sum())
    recall = float((mask & grow(sil)).sum()) / n_mask if n_mask else 0.0
    precision = float((sil & grow(mask)).sum()) / n_sil if n_sil else 0.0
    return recall, precision


def coverage(gaussians: "Gaussians", views: list[tuple["Camera", np.ndarray]], max_views: int = 16,
             max_side: int = 320, min_alpha: float = 0.5, tol_px: int = 1, min_mask_px: int = 9
             ) -> Coverage | None:
    """Silhouette coverage of `gaussians` (one object's cleaned splats) against `views`: [(camera, mask
    [H,W] bool of the object in that camera's image)]. Views whose mask has fewer than `min_mask_px`
    pixels at the render size are skipped (too small to measure a share of); of the rest at most
    `max_views`, spread evenly over the list. None when no view is left."""
    sized = []
    for cam, mask in views:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (cam.height, cam.width):
            continue  # not this camera's image (callers pair masks with cameras by view name)
        cam = dataclasses.replace(cam, dist=None)
        if max(cam.width, cam.height) > max_side:
            cam = cam.scaled(max_side / max(cam.width, cam.height))
        m = resample_mask(mask, cam.width, cam.height)
        if int(m.sum()) >= min_mask_px:
            sized.append((cam, m))
    if not sized:
        return None
    if len(sized) > max_views:
        sized = [sized[i] for i in np.unique(np.linspace(0, len(sized) - 1, max(max_views, 1)).round().astype(int))]
    per_view = [view_coverage(silhouette(gaussians, cam, min_alpha), m, tol_px) for cam, m in sized]
    rec = np.array([r for r, _ in per_view])
    prec = np.array([p for _, p in per_view])
    return Coverage(recall=float(np.median(rec)), precision=float(np.median(prec)), views=len(per_view),
                    per_view=per_view)


def mask_views(masks, frames) -> dict[int, list[tuple["Camera", np.ndarray]]]:
    """{label: [(camera, mask)]} of a MaskSet (`semantics.masks`) paired with the capture's frames by view
    name (frames: objects with `.name` and `.camera`, e.g. a dataset's frames in the twin frame). Masks of
    views that are no frame, or whose size is not the frame's image size, are left out."""
    by_name = {f.name: f.camera for f in frames}
    out: dict[int, list] = {}
    for view in masks.views:
        cam = by_name.get(view)
        if cam is None:
            continue
        for label, m in sorted(masks.masks.get(view, {}).items()):
            if np.shape(m) == (cam.height, cam.width):
                out.setdefault(int(label), []).append((cam, m))
    return out


def consistent_clusters(gaussians: "Gaussians", cluster_ids: np.ndarray, views: list[tuple["Camera", np.ndarray]],
                        candidates: list[int], min_precision: float = 0.9, max_views: int = 8,
                        max_side: int = 320) -> list[int]:
    """The clusters among `candidates` whose splats lie inside the object's masks: silhouette precision
    (median over views, see the module docstring) of at least `min_precision`. gaussians [N]: the object's
    splats; cluster_ids [N]: their DBSCAN cluster (-1 noise); views: [(camera, mask)] as for `coverage`.

    Why: DBSCAN's largest cluster drops floaters, but on a sparse real capture it also cuts off parts of
    the object itself (the real cake's dark side: 8 clusters beside the largest, 0.72 of its masks covered
    by the largest alone). A floater that fusion labelled lies off the object, so outside its masks in most
    other views; a cut-off part lies inside them in every view that sees it."""
    keep = []
    for k in candidates:
        cov = coverage(gaussians.subset(np.flatnonzero(cluster_ids == k)), views, max_views=max_views,
                       max_side=max_side)
        if cov is not None and cov.precision >= min_precision:
            keep.append(int(k))
    return keep
