"""`Gaussians`: a set of 3D Gaussians as plain numpy data (activated values) that saves/loads itself.

This is the hand-over object between reconstruction and the later stages (semantics, geometry, viewer).
Values are *activated*: scales in metres (not log), opacities in (0, 1) (not logits), unit wxyz
quaternions. The trainer's raw parameters live in `splattwin.splat.model`.

Arrays are stored as float64: the standard PLY stores float32 log-scales and logits, and the float64
exp/log (sigmoid/logit) round trip then returns exactly the same float32 values, so
`load_ply -> save_ply` is bit-exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.transforms import matrix_from_quat_wxyz

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2 SH coefficients per colour channel."""
    return (int(degree) + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of `num_sh_bases`; raises ValueError if `k` is not a square."""
    d = int(round(np.sqrt(k))) - 1
    if d < 0 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per channel is not (degree+1)^2")
    return d


def rgb_to_sh0(rgb: np.ndarray) -> np.ndarray:
    """RGB in [0,1] -> DC SH coefficient (colour = 0.5 + C0 * sh0)."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0


def sh0_to_rgb(sh0: np.ndarray) -> np.ndarray:
    """DC SH coefficient -> RGB (unclamped)."""
    return 0.5 + SH_C0 * np.asarray(sh0, dtype=np.float64)


@dataclass
class Gaussians:
    """N 3D Gaussians in the world frame.

    Attributes:
        means: [N,3] centres, world frame, metres.
        quats: [N,4] unit quaternions, wxyz, rotation Gaussian-frame -> world.
        scales: [N,3] standard deviations along the Gaussian's axes, metres (not log).
        opacities: [N] in (0, 1) (not logits).
        sh: [N,K,3] spherical-harmonics coefficients, K = (deg+1)^2; sh[:, 0] is DC
            (colour = 0.5 + C0 * sh0), the rest in the standard 3DGS/gsplat basis order.
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float64).reshape(-1, 3)
        n = self.means.shape[0]
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float64).reshape(n, 4)
        self.scales = np.ascontiguousarray(self.scales, dtype=np.float64).reshape(n, 3)
        self.opacities = np.ascontiguousarray(self.opacities, dtype=np.float64).reshape(n)
        sh = np.asarray(self.sh, dtype=np.float64)
        if sh.ndim == 2:  # [N,3] plain DC
            sh = sh[:, None, :]
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"sh must be [N,K,3] with N={n}, got {sh.shape}")
        sh_degree_from_bases(sh.shape[1])
        self.sh = np.ascontiguousarray(sh)

    # -- basic ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def colors(self) -> np.ndarray:
        """[N,3] RGB in [0,1] from the DC coefficient (view-independent base colour)."""
        return np.clip(sh0_to_rgb(self.sh[:, 0]), 0.0, 1.0)

    def subset(self, mask: np.ndarray) -> Gaussians:
        """Gaussians selected by a boolean mask [N] or an index array."""
        mask = np.asarray(mask)
        if mask.dtype == bool and mask.shape != (len(self),):
            raise ValueError(f"boolean mask must have shape ({len(self)},), got {mask.shape}")
        return Gaussians(self.means[mask], self.quats[mask], self.scales[mask], self.opacities[mask],
                         self.sh[mask])

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Copy truncated (or zero-padded) to SH degree `degree`."""
        k = num_sh_bases(degree)
        sh = np.zeros((len(self), k, 3))
        m = min(k, self.sh.shape[1])
        sh[:, :m] = self.sh[:, :m]
        return Gaussians(self.means.copy(), self.quats.copy(), self.scales.copy(), self.opacities.copy(), sh)

    def rotation_matrices(self) -> np.ndarray:
        """[N,3,3] rotation matrices of the (normalised) quaternions."""
        return matrix_from_quat_wxyz(self.quats)

    def covariances(self) -> np.ndarray:
        """[N,3,3] world-frame covariances R diag(s^2) R^T, m^2."""
        R = self.rotation_matrices()
        return (R * (self.scales**2)[:, None, :]) @ np.swapaxes(R, 1, 2)

    def validate(self, path: str | Path | None = None) -> None:
        """Raise InputError if any value is non-finite or out of range."""
        for name in ("means", "quats", "scales", "opacities", "sh"):
            a = getattr(self, name)
            if not np.all(np.isfinite(a)):
                bad = int(np.count_nonzero(~np.isfinite(a).reshape(len(self), -1).all(axis=1)))
                raise InputError(f"{bad} Gaussians have non-finite {name}", path)
        if np.any(self.scales < 0):
            raise InputError("negative scales", path)
        if np.any((self.opacities < 0) | (self.opacities > 1)):
            raise InputError("opacities outside [0, 1]", path)

    # -- I/O -----------------------------------------------------------------------------------
    def save_ply(self, path: str | Path) -> Path:
        """Write the standard 3DGS PLY (binary little-endian), atomically."""
        from splattwin.splat.ply import write_gaussians_ply

        return write_gaussians_ply(path, self)

    @classmethod
    def load_ply(cls, path: str | Path) -> Gaussians:
        """Read a 3DGS PLY (ours or another tool's; binary or ascii, any SH degree)."""
        from splattwin.splat.ply import read_gaussians_ply

        return read_gaussians_ply(path)

    @classmethod
    def empty(cls, sh_degree: int = 0) -> Gaussians:
        return cls(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0),
                   np.zeros((0, num_sh_bases(sh_degree), 3)))
