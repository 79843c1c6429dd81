"""CPU ray-casting renderer of the tabletop scene (Open3D `RaycastingScene`, Embree; no OpenGL).

Per pixel: the nearest hit's z-depth, the object label, and a Lambertian colour
`albedo * (ambient + diffuse * max(0, n.l) * lit)` from one directional light, with optional cast shadows
(`lit` from an occlusion ray towards the light). RGB is supersampled `s x s` per pixel (box filter) for
anti-aliased edges; depth and labels are taken at pixel centres (u + 0.5, v + 0.5), the convention of
`splattwin.capture.Camera`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from splattwin.capture.camera import Camera
from splattwin.scene import textures as tx

LIGHT_DIR = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])  # world, towards the light
AMBIENT = 0.38
DIFFUSE = 0.62
_MISS = 4294967295  # o3d INVALID_ID
_RAYS_PER_BATCH = 1 << 21  # supersampled rays shaded at once, per band (~0.5 GB of temporaries)
_BAND_ROWS = 32


@dataclass
class Surface:
    """A renderable surface: world-frame mesh, label id (0 = table/background), pose and albedo."""

    name: str
    label: int
    mesh_world: trimesh.Trimesh
    T_world_obj: np.ndarray
    albedo: tx.Albedo


def shade(albedo: np.ndarray, n_world: np.ndarray, lit: np.ndarray | None = None) -> np.ndarray:
    """Lambertian shading. albedo [N,3], n_world [N,3] unit, lit [N] in {0,1} or None. -> [N,3] float32"""
    ndl = np.clip(np.einsum("ij,j->i", n_world, LIGHT_DIR), 0.0, None)
    if lit is not None:
        ndl = ndl * lit
    return np.clip(albedo * (AMBIENT + DIFFUSE * ndl)[:, None], 0.0, 1.0).astype(np.float32)


class SceneRenderer:
    """Ray caster over a fixed list of surfaces. Thread-compatible; build once, render many views."""

    def __init__(self, surfaces: list[Surface], shadows: bool = True):
        self.surfaces = surfaces
        self.shadows = shadows
        self.scene = o3d.t.geometry.RaycastingScene()
        self.gid_to_index: dict[int, int] = {}
        for i, s in enumerate(surfaces):
            tm = o3d.t.geometry.TriangleMesh()
            tm.vertex.positions = o3d.core.Tensor(np.asarray(s.mesh_world.vertices, dtype=np.float32))
            tm.triangle.indices = o3d.core.Tensor(np.asarray(s.mesh_world.faces, dtype=np.int32))
            gid = self.scene.add_triangles(tm)
            self.gid_to_index[int(gid)] = i
        self._labels = np.zeros(max(self.gid_to_index) + 2, dtype=np.uint8)
        for gid, i in self.gid_to_index.items():
            self._labels[gid] = surfaces[i].label

    # -- rays ------------------------------------------------------------------------------------------
    @staticmethod
    def camera_rays(camera: Camera, supersample: int = 1, rows: tuple[int, int] | None = None) -> np.ndarray:
        """Rays through pixel (sub-)centres of pixel rows [r0, r1) (default all).
        -> [(r1-r0)*s, W*s, 6] float32 (origin, direction with z_cam = 1)."""
        s = int(supersample)
        r0, r1 = rows if rows is not None else (0, camera.height)
        K = camera.K.copy()
        K[:2] *= s  # sub-pixel (i + 0.5) / s of the original grid: s x s samples per pixel
        K[1, 2] -= r0 * s  # the band starts at pixel row r0
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            intrinsic_matrix=o3d.core.Tensor(K), extrinsic_matrix=o3d.core.Tensor(camera.T_cam_world),
            width_px=camera.width * s, height_px=(r1 - r0) * s)
        return rays.numpy()

    def cast(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays [...,6]. -> t [...] (ray parameter; z-depth for `camera_rays`), gid [...] uint32,
        normal [...,3] world."""
        ans = self.scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
        return {"t": ans["t_hit"].numpy(), "gid": ans["geometry_ids"].numpy(),
                "normal": ans["primitive_normals"].numpy()}

    def colour_hits(self, points: np.ndarray, normals: np.ndarray, gids: np.ndarray,
                    view_dirs: np.ndarray | None = None) -> np.ndarray:
        """Shaded colour of surface hits. points/normals [N,3] world, gids [N] -> [N,3] float32."""
        rgb = np.zeros((len(points), 3), dtype=np.float32)
        if view_dirs is not None:  # face normals towards the viewer (robust to any winding)
            flip = np.einsum("ij,ij->i", normals, view_dirs) > 0
            normals = np.where(flip[:, None], -normals, normals)
        lit = None
        if self.shadows and len(points):
            shadow_rays = np.empty((len(points), 6), dtype=np.float32)
            shadow_rays[:, :3] = points + normals * 1e-4
            shadow_rays[:, 3:] = LIGHT_DIR
            occ = self.scene.test_occlusions(o3d.core.Tensor(shadow_rays), tnear=1e-4).numpy()
            lit = (~occ).astype(np.float32)
        albedo = np.zeros_like(rgb)
        present = np.flatnonzero(np.bincount(gids.astype(np.int64), minlength=1))  # no sort of all samples
        for gid in present:
            sel = gids == gid
            surf = self.surfaces[self.gid_to_index[int(gid)]]
            # world -> object frame in float32 (sub-micrometre at tabletop scale; half the memory traffic of
            # float64). einsum, not `@`: a BLAS call per tiny 3x3 product is slow when the cores are contended
            R = surf.T_world_obj[:3, :3].astype(np.float32)
            t = surf.T_world_obj[:3, 3].astype(np.float32)
            p_obj = np.einsum("ij,jk->ik", points[sel] - t, R)
            n_obj = np.einsum("ij,jk->ik", normals[sel], R)
            albedo[sel] = surf.albedo(p_obj, n_obj)
        return shade(albedo, normals, lit)

    # -- images ----------------------------------------------------------------------------------------
    def render(self, camera: Camera, supersample: int = 5, threads: int | None = None) -> dict[str, np.ndarray]:
        """Render one view. -> rgb [H,W,3] float32 [0,1], depth [H,W] float32 metres (z, inf = miss),
        labels [H,W] uint8 (0 = table/background). threads: row bands shaded at once (default: the cores);
        the image does not depend on it."""
        H, W, s = camera.height, camera.width, int(supersample)
        centre_rays = self.camera_rays(camera, 1)
        centre = self.cast(centre_rays)
        hit = centre["gid"] != _MISS
        depth = np.where(hit, centre["t"], np.inf).astype(np.float32)
        labels = np.zeros((H, W), dtype=np.uint8)
        labels[hit] = self._labels[centre["gid"][hit]]

        rgb = np.empty((H, W, 3), dtype=np.float32)
        # bands of rows: bounded memory at any size and supersampling, and work for every core (numpy and
        # Open3D release the GIL in the large array operations). The band height is fixed, not derived from
        # the core count: the rays of a band are computed from a shifted principal point, so the banding
        # changes float rounding and must be the same on every machine for byte-identical scenes.
        workers = max(1, threads if threads is not None else min(8, os.cpu_count() or 1))
        band = max(1, min(_RAYS_PER_BATCH // (W * s * s), _BAND_ROWS))

        def do_band(r0: int) -> None:
            r1 = min(H, r0 + band)
            if s == 1:  # the centre rays already cast
                rays = centre_rays[r0:r1].reshape(-1, 6)
                ans = {k: v[r0:r1].reshape(-1, *v.shape[2:]) for k, v in centre.items()}
            else:
                rays = self.camera_rays(camera, s, (r0, r1)).reshape(-1, 6)
                ans = self.cast(rays)
            rgb[r0:r1] = self._shade_rays(rays, ans).reshape(r1 - r0, s, W, s, 3).mean(axis=(1, 3))

        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(do_band, range(0, H, band)))
        return {"rgb": rgb, "depth": depth, "labels": labels}

    def _shade_rays(self, rays: np.ndarray, ans: dict[str, np.ndarray]) -> np.ndarray:
        """Colour of rays [N,6] given their cast results (flat). -> [N,3] float32"""
        gid = ans["gid"].reshape(-1)
        t = ans["t"].reshape(-1)
        m = gid != _MISS
        dirs = rays[:, 3:]
        rgb = np.empty((len(rays), 3), dtype=np.float32)
        unit = dirs / np.sqrt(np.einsum("ij,ij->i", dirs, dirs))[:, None]
        rgb[~m] = tx.background_rgb(unit[~m])
        hit = rays[m]
        pts = hit[:, :3] + hit[:, 3:] * t[m, None]
        rgb[m] = self.colour_hits(pts, ans["normal"].reshape(-1, 3)[m], gid[m], unit[m])
        return rgb
