"""Stage 2: connectivity pruning (paper section 3.3.2) and the table plane of the background.

DBSCAN is scikit-learn's. For speed the points are first averaged per voxel (default eps / 4) and the
voxel centroids are clustered with `sample_weight` = points per voxel, so `min_samples` keeps its
meaning (points within about eps: centroids move by at most a voxel diagonal) while the neighbour
search handles ~10x fewer samples with ~10x fewer neighbours each; voxel = 0 runs
exact DBSCAN on the points. The table plane is our own seeded RANSAC (`ransac_plane`, numpy) rather than
Open3D's `segment_plane`: Open3D's samples hypotheses on several threads from one generator, so even with
`o3d.utility.random.seed` the same points give different planes from run to run (isl-org/Open3D#7270; seen
here as two table heights 8 µm apart and a different hammer mesh between a build and its resumed copy),
and a twin must be reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def voxel_groups(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group points [N,3] by voxel. Returns (centroids [M,3], counts [M], inverse [N] voxel id per point)."""
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]  # 1D keys: unique is ~10x faster
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    centroids = np.stack([np.bincount(inverse, weights=points[:, k]) for k in range(3)], axis=1) / counts[:, None]
    return centroids, counts, inverse


def dbscan_labels(points: np.ndarray, eps: float, min_samples: int, voxel: float = 0.0) -> np.ndarray:
    """DBSCAN cluster id per point [N] (int, -1 = noise). voxel > 0: weighted DBSCAN on voxel centroids."""
    from sklearn.cluster import DBSCAN

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    if voxel and voxel > 0:
        centroids, counts, inverse = voxel_groups(points, voxel)
        lab = DBSCAN(eps=eps, min_samples=min_samples, n_jobs=-1).fit(centroids, sample_weight=counts).labels_
        return lab[inverse]
    return DBSCAN(eps=eps, min_samples=min_samples, n_jobs=-1).fit(points).labels_


def largest_cluster(points: np.ndarray, eps: float = 0.02, min_samples: int = 10, voxel: float = 0.0) -> np.ndarray:
    """Keep-mask [N] of the largest DBSCAN cluster (by point count); all False when everything is noise."""
    lab = dbscan_labels(points, eps, min_samples, voxel)
    valid = lab >= 0
    if not valid.any():
        return np.zeros(len(lab), dtype=bool)
    best = np.bincount(lab[valid]).argmax()
    return lab == best


@dataclass
class Plane:
    """Plane n . p + d = 0 with unit normal n pointing up (+z side), twin frame, metres."""

    normal: np.ndarray
    d: float

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """[N] height of points [N,3] above the plane (m)."""
        return points @ self.normal + self.d


def ransac_plane(points: np.ndarray, distance: float, iterations: int, rng: np.random.Generator,
                 chunk: int = 64) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane of points [N,3] (N >= 3): (unit normal [3], d, inlier indices [K]) of the hypothesis
    through 3 random points with the most points within `distance` (m; ties: the first drawn).
    Deterministic for a given generator state; `chunk` hypotheses are scored at a time ([chunk, N] floats)."""
    pts = np.asarray(points, dtype=np.float64)
    tri = rng.integers(0, len(pts), size=(max(1, iterations), 3))
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12                     # repeated or collinear samples define no plane
    n = np.where(ok[:, None], n / np.maximum(norm, 1e-300)[:, None], 0.0)
    d = -np.einsum("ij,ij->i", n, a)
    counts = np.full(len(n), -1, dtype=np.int64)
    for i in range(0, len(n), chunk):
        dist = np.abs(pts @ n[i:i + chunk].T + d[i:i + chunk])       # [N, chunk]
        counts[i:i + chunk] = np.where(ok[i:i + chunk], (dist <= distance).sum(axis=0), -1)
    best = int(np.argmax(counts))
    if counts[best] < 0:                  # every sample degenerate (e.g. all points on one line)
        raise ValueError("no plane through the points: they are collinear or repeated")
    return n[best], float(d[best]), np.flatnonzero(np.abs(pts @ n[best] + d[best]) <= distance)


def fit_plane(points: np.ndarray, distance: float = 0.004, iterations: int = 500, max_samples: int = 30000,
              seed: int = 0, max_tilt_deg: float | None = 30.0, tries: int = 4) -> Plane:
    """Dominant (near-horizontal) plane of points [N,3] by RANSAC (`ransac_plane`), refined by least squares.
    The same points and seed give the same plane, bit for bit.

    max_tilt_deg: planes tilted more than this from the xy plane (walls, box sides) are set aside and the
    search repeats on the remaining points, up to `tries` planes; None accepts any plane."""
    rng = np.random.default_rng(seed)
    pts = points if len(points) <= max_samples else points[rng.choice(len(points), max_samples, replace=False)]
    first = None
    for _ in range(max(1, tries)):
        try:
            n, _, inl = ransac_plane(pts, distance, iterations, rng)
        except ValueError:
            if first is None:
                raise
            n, pts, inl = first   # what is left of the points after a wall holds no plane
            break
        first = first or (n, pts, inl)
        if max_tilt_deg is None or abs(n[2]) >= np.cos(np.radians(max_tilt_deg)):
            break
        keep = np.ones(len(pts), dtype=bool)
        keep[inl] = False
        if keep.sum() < 3:
            break
        pts = pts[keep]
    else:
        n, pts, inl = first  # no horizontal plane found: the dominant one
    if max_tilt_deg is not None and abs(n[2]) < np.cos(np.radians(max_tilt_deg)):
        n, pts, inl = first
    # least-squares refinement (SVD of the inliers) for an unbiased height
    q = pts[inl]
    centre = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - centre, full_matrices=False)
    n2 = vt[2]
    if np.dot(n2, n) < 0:
        n2 = -n2
    if n2[2] < 0:  # normal towards +z (the twin frame is z up)
        n2 = -n2
    return Plane(normal=n2, d=float(-n2 @ centre))


@dataclass
class BackgroundSplit:
    """Background points classified (masks [N] over the input points)."""

    plane: Plane
    table: np.ndarray        # supporting surface
    obstacles: np.ndarray    # real obstacles standing on the table
    obstacle_ids: np.ndarray  # [N] obstacle cluster id, -1 elsewhere

    @property
    def keep(self) -> np.ndarray:
        return self.table | self.obstacles


def split_background(points: np.ndarray, eps: float = 0.02, min_samples: int = 10, voxel: float = 0.0,
                     plane_distance: float = 0.004, plane_iterations: int = 500, support_gap: float = 0.02,
                     obstacle_min_points: int = 200, seed: int = 0, plane: Plane | None = None) -> BackgroundSplit:
    """Table plane + obstacles of background points [N,3]; floaters and points under the table dropped.

    The supporting surface is the largest connected part of the plane inliers (within 2x plane_distance);
    obstacles are clusters above the plane with at least `obstacle_min_points` points whose lowest point is
    within `support_gap` of the plane (floaters hover, real things stand). plane: the table plane when it
    is already known (a frame built on the table: z = 0), used instead of a RANSAC fit.
    """
    n = len(points)
    plane = plane if plane is not None else fit_plane(points, plane_distance, plane_iterations, seed=seed)
    h = plane.signed_distance(points)
    near = np.abs(h) <= 2.0 * plane_distance
    table = np.zeros(n, dtype=bool)
    if near.any():  # a dense plane: coarser voxels (eps / 2) keep the same connectivity, 4x fewer samples
        table[np.flatnonzero(near)[largest_cluster(points[near], eps, min_samples, max(voxel, eps / 2) if voxel else 0.0)]] = True
    above = h > 2.0 * plane_distance
    obstacles = np.zeros(n, dtype=bool)
    ids = np.full(n, -1, dtype=np.int64)
    if above.sum() >= min_samples:
        idx = np.flatnonzero(above)
        lab = dbscan_labels(points[idx], eps, min_samples, voxel)
        next_id = 0
        for c in np.unique(lab[lab >= 0]):
            sel = idx[lab == c]
            if len(sel) >= obstacle_min_points and h[sel].min() <= support_gap:
                obstacles[sel] = True
                ids[sel] = next_id
                next_id += 1
    return BackgroundSplit(plane=plane, table=table, obstacles=obstacles, obstacle_ids=ids)


def foot_bleed_mask(points: np.ndarray, support_z: float, foot_height: float = 0.006, margin: float = 0.005,
                    min_above: int = 50) -> np.ndarray:
    """Keep-mask [N] of an object's points [N,3] (twin frame, z up, m) without the table splats that
    mask lifting gave it at its foot (shadows, contact edges: 2D masks bleed onto the table around the
    object). A point within `foot_height` of the support plane z = support_z that lies more than
    `margin` (horizontally) from every point of the object above that layer is table, not object: a
    resting object does not reach out along the table beyond its own outline. Objects with fewer than
    `min_above` points above the layer (flat things lying on the table) are left alone."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    low = points[:, 2] - support_z < foot_height
    keep = np.ones(len(points), dtype=bool)
    if low.any() and (~low).sum() >= min_above:
        d, _ = cKDTree(points[~low, :2]).query(points[low, :2], workers=-1)
        keep[np.flatnonzero(low)[d > margin]] = False
    return keep
