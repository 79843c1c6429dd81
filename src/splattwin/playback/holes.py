"""Fill the table under a picked object: the capture never saw it, so nothing in the splats is there.

Method (ours: no library inpaints Gaussians): on a 2 mm grid of the table plane, the object's *footprint*
is the cells under its Gaussians (and those of the background that bleed into it), closed, hole-filled
and dilated by `margin`. Every footprint cell p takes the table Gaussians of its mirror cell across the
footprint's boundary, s = 2 b - p with b the nearest cell outside (scipy's exact Euclidean distance
transform gives b), translated by p - s. Mirroring keeps the table's texture continuous across the
boundary and its density unchanged. Cells deeper than `depth` (MIRROR_DEPTH) inside fold back and forth
(a triangle wave along the same normal), so the source always lies within `depth` of the boundary: a plain
mirror copied the table as far out as the footprint's inradius, and whatever lay there -- on the demo the
target frame's orange tape 3.3 cm beyond the blue box's footprint -- reappeared as a blob in the middle
of the hole. Mirror cells that fall off the grid or in another footprint fall back to b itself.

The result is a `HoleFill` per object: the fill Gaussians, the footprint cells (for the report's mark)
and the background Gaussians the fill replaces (object residue at the foot, contact shadow under the
object), which `DynamicScene` hides once the object has left its place.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from splattwin.splat.gaussians import Gaussians

CELL = 0.002          # m, grid cell
MARGIN = 0.015        # m, footprint dilation: residue and contact shadow at the object's foot (bench: 1.0-2.0 cm best)
TABLE_BAND = 0.006    # m, |z - table_height| of the Gaussians that make the table surface
# m, how far beyond the footprint the mirror copies from (deeper cells fold back). bench/photoreal.py psnr_filled
# on the demo: 19.99 dB unlimited (the footprint's inradius, ~5 cm), 20.45 at 2 cm; a sweep of the same measure
# (its fallback for blocked cells slightly different) gave 19.8 at 1.5 cm, 20.2 at 2.5 cm, 20.1 at 3 cm
MIRROR_DEPTH = 0.02


@dataclass
class HoleFill:
    """The filled region under one object (twin frame, m).

    gaussians: the fill; outline_xy [M,2]: the footprint's convex outline on the table (for drawing);
    area_m2: footprint area; hidden: indices into the background Gaussians replaced by the fill (hidden
    once the object moved); cells_xy [C,2]: centres of the footprint cells; source: [len(gaussians)] the
    background Gaussian each fill Gaussian copies (the re-lighting takes its capture-time shadow from it).
    """

    object: str
    gaussians: Gaussians
    outline_xy: np.ndarray
    area_m2: float
    hidden: np.ndarray
    cells_xy: np.ndarray
    table_height: float
    method: str = "table Gaussians mirrored across the footprint boundary"
    source: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def to_dict(self) -> dict:
        """Summary for reports (JSON-ready)."""
        return {"object": self.object, "area_m2": round(float(self.area_m2), 6),
                "fill_gaussians": len(self.gaussians), "hidden_gaussians": int(len(self.hidden)),
                "outline_xy": np.round(self.outline_xy, 4).tolist(), "table_height": float(self.table_height),
                "method": self.method}


def _outline(xy: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) < 3:
        return xy.copy()
    try:
        return xy[ConvexHull(xy).vertices]
    except QhullError:
        return xy[:3].copy()


def mirror_source(p: np.ndarray, b: np.ndarray, t: np.ndarray, depth: float) -> np.ndarray:
    """[N,2] grid cells the footprint cells p [N,2] copy: the mirror b + (b - p) across their nearest outside
    cells b [N,2] (t [N] = |b - p| > 0, cells), with the distance beyond b folded into [0, depth] (cells;
    a triangle wave, so neighbouring cells still copy neighbouring cells): equal to 2 b - p where t <= depth."""
    t = np.asarray(t, float)
    period = np.mod(t, 2 * depth)
    folded = np.where(period > depth, 2 * depth - period, period)
    return np.rint(b + (b - p) * (folded / t)[:, None]).astype(np.int64)


def fill_hole(name: str, object_means_world: np.ndarray, background: Gaussians, table_height: float,
              cell: float = CELL, margin: float = MARGIN, band: float = TABLE_BAND,
              other_footprints: list[np.ndarray] | None = None, depth: float = MIRROR_DEPTH) -> HoleFill:
    """The fill under one object at its twin pose.

    Args:
        object_means_world: [M,3] the object's Gaussian centres at its twin pose (twin frame, m).
        background: the static Gaussians (twin frame); the table surface is those within `band` of
            `table_height`.
        other_footprints: [K,2] xy points of other objects: mirror cells there hold no seen table.
        depth: m, the mirror's sources lie at most this far outside the footprint (deeper cells fold back).
    """
    from scipy import ndimage

    h = float(table_height)
    pts = np.asarray(object_means_world, float)
    pts = pts[pts[:, 2] > h - band]   # below the table: floaters, not footprint
    if len(pts) == 0:
        return HoleFill(name, Gaussians.empty(background.sh_degree), np.zeros((0, 2)), 0.0,
                        np.zeros(0, np.int64), np.zeros((0, 2)), h)
    lo = pts[:, :2].min(0) - margin
    hi = pts[:, :2].max(0) + margin
    span = hi - lo
    ring = float(np.max(span)) / 2 + 2 * cell   # the mirror reaches at most the inradius outside
    g0 = lo - ring
    n = np.ceil((span + 2 * ring) / cell).astype(int) + 1
    ij = lambda xy: np.floor((xy - g0) / cell).astype(np.int64)  # noqa: E731

    foot = np.zeros((n[0], n[1]), bool)
    c = ij(pts[:, :2])
    foot[c[:, 0], c[:, 1]] = True
    foot = ndimage.binary_closing(foot, iterations=2)
    foot = ndimage.binary_fill_holes(foot)
    foot = ndimage.binary_dilation(foot, iterations=max(1, int(round(margin / cell))))

    blocked = np.zeros_like(foot)
    for other in other_footprints or []:
        oc = ij(np.asarray(other)[:, :2])
        ok = np.all((oc >= 0) & (oc < n), axis=1)
        blocked[oc[ok, 0], oc[ok, 1]] = True
    blocked = ndimage.binary_dilation(blocked, iterations=max(1, int(round(margin / cell)))) & ~foot

    # nearest outside cell b of every footprint cell p, at distance t; mirror s = 2 b - p = b + (b - p), its
    # depth beyond b folded into [0, depth] so that nothing farther out than `depth` is copied
    dist, (bi, bj) = ndimage.distance_transform_edt(foot, return_indices=True)
    pi, pj = np.nonzero(foot)
    b = np.stack([bi[pi, pj], bj[pi, pj]], 1)
    p = np.stack([pi, pj], 1)
    s = mirror_source(p, b, dist[pi, pj], max(depth / cell, 1.0))
    bad = np.any((s < 0) | (s >= n), axis=1)
    s[bad] = b[bad]
    sb = blocked[s[:, 0], s[:, 1]] | foot[s[:, 0], s[:, 1]]
    s[sb] = b[sb]

    # table Gaussians binned by cell
    bz = background.means[:, 2]
    bc = ij(background.means[:, :2])
    inside = np.all((bc >= 0) & (bc < n), axis=1)
    table = np.flatnonzero(inside & (np.abs(bz - h) < band))
    key_t = bc[table, 0] * n[1] + bc[table, 1]
    order = np.argsort(key_t, kind="stable")
    key_sorted = key_t[order]
    src_key = s[:, 0] * n[1] + s[:, 1]
    start = np.searchsorted(key_sorted, src_key, "left")
    stop = np.searchsorted(key_sorted, src_key, "right")
    counts = stop - start
    rep = np.repeat(np.arange(len(p)), counts)
    offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    src = table[order[np.repeat(start, counts) + offs]]
    shift = (p[rep] - s[rep]) * cell
    fill = background.subset(src)
    fill.means = fill.means.copy()
    fill.means[:, :2] += shift
    fill.means[:, 2] = h + (fill.means[:, 2] - h)   # keep each copy's own height above the plane

    # background Gaussians over the footprint (residue, contact shadow) are replaced by the fill
    top = float(pts[:, 2].max()) + margin
    hidden = np.flatnonzero(inside & (bz < top) & (bz > h - band))
    hidden = hidden[foot[bc[hidden, 0], bc[hidden, 1]]]
    cells_xy = g0 + (p + 0.5) * cell
    return HoleFill(name, fill, _outline(cells_xy), float(len(p)) * cell * cell, hidden, cells_xy, h, source=src)
