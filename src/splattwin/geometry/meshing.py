"""Stage 3: collision-ready meshing via alpha shapes (paper section 3.3.3), repair and simplification.

Alpha shapes (Open3D) of points sampled on a surface give a thin shell: an outer and an inner sheet,
rarely manifold. So the surface points (Gaussian centres plus each splat's half-opaque ellipsoid,
`ellipsoid_samples`: trained centres sit inside the surface they render) first become a voxel solid
(occupancy, morphological closing, hole filling: scipy.ndimage; for an object resting on the table also
everything between the table and what was seen of it, since trained splats leave unseen sides nearly
empty and the shell open); the alpha shape is taken of that solid's points, building the Delaunay
`TetraMesh` once and trying the radii `alpha_factors x point spacing` in order; the outer component of
the first watertight result is kept.
When none is watertight after trimesh's repair we fall back, with the named warning
`MeshRepairWarning`, to a voxel remesh (scikit-image marching cubes of the same solid), then to the
convex hull. Simplification (quadric decimation) is only accepted when the result is still watertight.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import trimesh

from splattwin.geometry.clustering import voxel_groups


class MeshRepairWarning(UserWarning):
    """Meshing could not make a watertight alpha-shape mesh; a fallback shape was used."""


@dataclass
class MeshResult:
    """A watertight mesh and how it was made. method: 'alpha' | 'convex_hull'."""

    mesh: trimesh.Trimesh
    method: str
    alpha: float | None = None
    spacing: float | None = None
    notes: list = field(default_factory=list)


def downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Voxel-averaged points [M,3] (one centroid per occupied voxel of side `voxel` m)."""
    if voxel <= 0 or len(points) == 0:
        return np.asarray(points, dtype=np.float64)
    return voxel_groups(np.asarray(points, dtype=np.float64), voxel)[0]


def level_radii(opacities: np.ndarray, level: float = 0.5) -> np.ndarray:
    """[N] Mahalanobis radius at which each Gaussian's own alpha, opacity * exp(-r^2/2), falls to
    `level`: sqrt(2 ln(opacity / level)); 0 for opacities at or below the level (such a splat is never
    that opaque on its own: only its centre is kept)."""
    o = np.asarray(opacities, dtype=np.float64)
    return np.sqrt(2.0 * np.log(np.maximum(o / level, 1.0)))


def ellipsoid_samples(means: np.ndarray, rotations: np.ndarray, scales: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Points [N*26,3] on each Gaussian's ellipsoid of Mahalanobis radius radii[N] (world frame, m).

    means [N,3], rotations [N,3,3] (Gaussian -> world), scales [N,3] std devs. Directions: the 26 of a
    3x3x3 stencil (axes, edge and corner diagonals), normalised; deterministic, because the voxel solid
    keeps the samples' outer envelope, and a random sampling's envelope grows with the sample count.
    With `level_radii` these are the splats' alpha = level iso-surfaces: trained 3DGS surface splats are
    flat discs whose thin axis follows the surface normal and whose centres sit ~1-2 sigma *inside*
    the surface they render (measured on the demo twin: -1.5 mm on tops, -2.5 to -4.5 mm on sides);
    the union of the half-opaque ellipsoids is where the object visibly is. Inner samples fall inside
    the solid, so no normal orientation is needed."""
    d = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
                 dtype=np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    local = d[None] * (scales * np.asarray(radii, dtype=np.float64)[:, None])[:, None, :]
    return (np.einsum("nij,nsj->nsi", rotations, local) + means[:, None, :]).reshape(-1, 3)


def add_bottom(points: np.ndarray, spacing: float, z_floor: float | None = None) -> np.ndarray:
    """Points [N,3] plus their footprint projected onto z = z_floor (default: their lowest z).

    An object resting on the table is never seen from below; closing it at the contact plane gives the
    alpha shape a closed bottom (the physically right answer for collision).
    """
    z0 = points[:, 2].min() if z_floor is None else z_floor
    foot = points.copy()
    foot[:, 2] = z0
    foot = downsample(foot, spacing)
    foot[:, 2] = z0
    return np.concatenate([points, foot], axis=0)


@dataclass
class VoxelSolid:
    """Occupancy grid of a solid. occ [X,Y,Z] bool; voxel (i,j,k) covers origin + [i,i+1) * pitch (m)."""

    occ: np.ndarray
    origin: np.ndarray
    pitch: float

    def points(self, interior_stride: int = 2) -> np.ndarray:
        """Voxel centres [M,3]: the boundary layer plus every `interior_stride`-th interior voxel — enough
        for the alpha complex to be solid, so alpha shapes give one outer surface (surface-only samples
        give the double sheet of a thin shell)."""
        from scipy import ndimage

        st = ndimage.generate_binary_structure(3, 1)  # face neighbours: the thinnest closed boundary layer
        boundary = self.occ & ~ndimage.binary_erosion(self.occ, st, border_value=0)
        keep = boundary
        if interior_stride >= 1:
            grid = np.indices(self.occ.shape)
            keep = boundary | (self.occ & np.all(grid % interior_stride == 0, axis=0))
        # tiny deterministic jitter: grid points are co-spherical, which makes the Delaunay degenerate
        jitter = np.random.default_rng(0).uniform(-0.05, 0.05, (int(keep.sum()), 3))
        return (np.argwhere(keep) + 0.5 + jitter) * self.pitch + self.origin


def voxel_solid(points: np.ndarray, pitch: float, close_iterations: int = 2, max_extra: int = 2,
                floor_z: float | None = None) -> VoxelSolid:
    """Solid enclosed by surface points [N,3] (m): occupancy at `pitch`, morphological closing
    (`close_iterations` voxels, 26-neighbourhood) to seal sampling gaps, interior filled
    (scipy binary_fill_holes). When filling finds no interior (the shell still leaks) the closing is
    widened by up to `max_extra` voxels; a truly thin object stays a sheet.

    floor_z: height (same frame, z up) of the support an object rests on. Then every voxel between the
    floor and an occupied voxel above it is solid too (support extrusion). Trained splats leave faces
    that no camera saw well nearly empty (a box's back side: ~20 Gaussians on 150 cm^2), so the
    shell leaks and hole filling finds no interior; a resting object is solid under what was seen of
    it, exactly so without overhangs and conservatively (never thinner) with them."""
    from scipy import ndimage

    points = np.asarray(points, dtype=np.float64)
    pad = close_iterations + max_extra + 2
    origin = points.min(axis=0) - pad * pitch
    if floor_z is not None:  # floor on a layer of voxel centres: the meshed bottom lies on the support, not up to a voxel above it
        origin[2] = floor_z - (np.ceil((floor_z - origin[2]) / pitch - 0.5) + 0.5) * pitch
    ijk = np.floor((points - origin) / pitch).astype(np.int64)
    occ = np.zeros(ijk.max(axis=0) + pad + 1, dtype=bool)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    st = np.ones((3, 3, 3), dtype=bool)
    for it in range(close_iterations, close_iterations + max_extra + 1):
        shell = ndimage.binary_dilation(occ, st, iterations=it)
        filled = ndimage.binary_fill_holes(shell)
        if filled.sum() > 1.02 * shell.sum():  # found an enclosed interior
            break
    solid = ndimage.binary_erosion(filled, st, iterations=it, border_value=0) | occ
    if floor_z is not None:
        k_floor = int(np.floor((floor_z - origin[2]) / pitch))
        below_top = np.flip(np.logical_or.accumulate(np.flip(solid, axis=2), axis=2), axis=2)
        below_top[:, :, :max(k_floor, 0)] = False
        solid |= below_top
    return VoxelSolid(occ=solid, origin=origin, pitch=float(pitch))


def marching_cubes_mesh(solid: VoxelSolid, smooth: float = 0.7) -> trimesh.Trimesh:
    """Watertight, outward-oriented surface of a voxel solid (scikit-image marching cubes, level 0.5
    of the occupancy blurred by `smooth` voxels, so the surface lies on the voxel faces)."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    field_ = np.pad(solid.occ.astype(np.float32), 1)
    if smooth > 0:
        field_ = ndimage.gaussian_filter(field_, smooth)
    v, f, _, _ = marching_cubes(field_, 0.5)
    m = trimesh.Trimesh((v - 1 + 0.5) * solid.pitch + solid.origin, f, process=True)
    if m.volume < 0:
        m.invert()
    return m


def point_spacing(points: np.ndarray, k: int = 1) -> float:
    """Median distance from each point [N,3] to its k-th nearest neighbour (m). k = 1: the nearest;
    larger k measures the sampling's gaps better (random samples cluster)."""
    from scipy.spatial import cKDTree

    if len(points) <= k:
        return 0.0
    d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    return float(np.median(d[:, k]))


def _outer_watertight(m: trimesh.Trimesh) -> trimesh.Trimesh | None:
    """Outer closed component (largest bounding box) of an alpha-shape mesh, oriented outwards; None if
    it is not watertight. Components: scipy connected components of the face-adjacency graph (faces
    sharing an edge), cheaper than trimesh's split + repair on meshes of this size."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(m.faces)
    V = np.asarray(m.vertices)
    if len(F) == 0:
        return None
    adj = m.face_adjacency
    nf = len(F)
    _, fcomp = connected_components(coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(nf, nf)),
                                    directed=False)
    # bounding-box volume per component, vectorised (there can be thousands of tiny ones)
    order = np.argsort(fcomp, kind="stable")
    fc = fcomp[order]
    starts = np.r_[0, np.flatnonzero(np.diff(fc)) + 1]
    tri = V[F[order]]
    lo = np.minimum.reduceat(tri.min(axis=1), starts, axis=0)
    hi = np.maximum.reduceat(tri.max(axis=1), starts, axis=0)
    best = fc[starts[np.argmax(np.prod(hi - lo, axis=1))]]
    outer = trimesh.Trimesh(V, F[fcomp == best], process=False)
    outer.remove_unreferenced_vertices()
    outer.update_faces(outer.unique_faces())
    if not outer.is_watertight:
        return None
    # consistent winding: Open3D's C++ orientation (trimesh's fix_winding is ~30x slower here)
    import open3d as o3d

    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(outer.vertices)),
                                   o3d.utility.Vector3iVector(np.asarray(outer.faces, dtype=np.int32)))
    if not om.orient_triangles():
        return None
    outer = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles), process=False)
    if not outer.is_winding_consistent:
        return None
    if outer.volume < 0:
        outer.invert()
    return outer if outer.is_volume else None


def alpha_shape_mesh(points: np.ndarray, alpha: float | None = None,
                     alpha_factors: tuple = (1.5, 2.0, 3.0), name: str = "mesh") -> MeshResult | None:
    """Watertight outer shell of the alpha shape of points [N,3] (m), or None when no alpha gives one.

    alpha None: try `alpha_factors x point_spacing` in order (the Delaunay TetraMesh is built once)."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    points = np.asarray(points, dtype=np.float64)
    spacing = point_spacing(points)
    if len(points) < 4 or spacing <= 0:
        return None
    tries = [alpha] if alpha is not None else [f * spacing for f in alpha_factors]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    try:
        tet, idx = o3d.geometry.TetraMesh.create_from_point_cloud(pc)  # once, reused for every alpha
    except RuntimeError:  # flat input: qhull fails
        return None
    for a in tries:
        m = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pc, a, tet, idx)
        tm = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles), process=False)
        outer = _outer_watertight(tm)
        if outer is not None:
            return MeshResult(outer, "alpha", alpha=float(a), spacing=spacing)
    return None


def solid_mesh(points: np.ndarray, pitch: float, alpha: float | None = None, alpha_factors: tuple = (1.5, 2.0, 3.0),
               close_iterations: int = 2, use_alpha: bool = True, name: str = "mesh",
               max_points: int = 12000, floor_z: float | None = None) -> MeshResult:
    """Watertight mesh of the solid enclosed by surface points [N,3] (m).

    Alpha shape of the voxel solid's points first (the paper's shrink-wrap); if no alpha gives a
    watertight outer shell, the voxel remesh (marching cubes) of the same solid; then the convex hull.
    Each fallback emits MeshRepairWarning naming the object. Objects whose solid would exceed
    `max_points` alpha-shape points get a coarser voxel (the Delaunay dominates the cost).
    floor_z: support height for `voxel_solid`'s support extrusion (None: off).
    """
    points = np.asarray(points, dtype=np.float64)
    solid = voxel_solid(points, pitch, close_iterations, floor_z=floor_z)
    notes = []
    if use_alpha:
        sp = solid.points()
        if len(sp) > max_points:  # Delaunay cost ~ points: coarsen big objects (points ~ area ~ pitch^-2)
            solid = voxel_solid(points, pitch * np.sqrt(len(sp) / max_points), close_iterations, floor_z=floor_z)
            sp = solid.points()
        res = alpha_shape_mesh(sp, alpha, alpha_factors, name)
        if res is not None:
            return res
        notes.append("alpha shape not watertight after repair")
    try:
        m = marching_cubes_mesh(solid)
        if m.is_watertight and m.is_volume and len(m.split()) == 1:
            if use_alpha:
                warnings.warn(MeshRepairWarning(f"{name}: alpha shape not watertight after repair, using the voxel remesh"),
                              stacklevel=2)
            return MeshResult(m, "voxel_remesh", spacing=pitch, notes=notes)
        notes.append("voxel remesh not a single closed volume")
    except (ValueError, RuntimeError, ImportError) as e:  # ImportError: scikit-image missing
        notes.append(f"voxel remesh failed: {e}")
    warnings.warn(MeshRepairWarning(f"{name}: {'; '.join(notes)}; using the convex hull"), stacklevel=2)
    return MeshResult(trimesh.convex.convex_hull(points), "convex_hull", spacing=pitch, notes=notes)


def smooth(mesh: trimesh.Trimesh, iterations: int = 10) -> trimesh.Trimesh:
    """Taubin smoothing (Open3D; volume-preserving, moves vertices only, so a watertight mesh stays
    watertight): removes the voxel staircase of alpha shapes / marching cubes before decimation."""
    import open3d as o3d

    if iterations <= 0:
        return mesh
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                   o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
    om = om.filter_smooth_taubin(number_of_iterations=int(iterations))
    out = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles), process=False)
    return out if out.is_watertight and out.volume > 0 else mesh


def simplify(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """Mesh decimated to at most `max_faces` (quadric error metric, Open3D; it keeps closed meshes
    closed where fast-simplification often opens them); returned unchanged if the result is not a
    watertight volume."""
    import open3d as o3d

    if len(mesh.faces) <= max_faces:
        return mesh
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                   o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
    sm = om.simplify_quadric_decimation(int(max_faces))
    s = trimesh.Trimesh(np.asarray(sm.vertices), np.asarray(sm.triangles), process=True)
    if len(s.faces) == 0 or not s.is_watertight:
        return mesh
    if s.volume < 0:
        s.invert()
    return s if s.is_volume else mesh
