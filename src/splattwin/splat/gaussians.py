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

from splattwin.equality import dataclass_eq
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


def _as_f64(a, name: str) -> np.ndarray:
    try:
        return np.ascontiguousarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a numeric array ({e})") from None


def _shape_str(shape: tuple[int, ...]) -> str:
    return "[" + ",".join(str(d) for d in shape) + "]"


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

    __eq__ = dataclass_eq   # array-aware: `g == Gaussians.load_ply(p)` (splattwin.equality)

    def __post_init__(self) -> None:
        """Checks the shapes exactly (ValueError naming the array, the expected and the given shape; no
        reshaping) and the values (`validate`: InputError). O(N) numpy checks: Gaussians are built once
        per stage hand-over, never per training step."""
        self.means = _as_f64(self.means, "means")
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"means must be [N,3], got shape {self.means.shape}")
        n = self.means.shape[0]
        self.quats = _as_f64(self.quats, "quats")
        self.scales = _as_f64(self.scales, "scales")
        self.opacities = _as_f64(self.opacities, "opacities")
        for name, want in (("quats", (n, 4)), ("scales", (n, 3)), ("opacities", (n,))):
            got = getattr(self, name).shape
            if got != want:
                raise ValueError(f"{name} must be {_shape_str(want)} with N={n} (the number of means), "
                                 f"got shape {got}")
        sh = _as_f64(self.sh, "sh")
        if sh.ndim == 2 and sh.shape == (n, 3):  # [N,3] plain DC
            sh = sh[:, None, :]
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"sh must be [N,K,3] (or [N,3] DC only) with N={n}, got shape {sh.shape}")
        sh_degree_from_bases(sh.shape[1])
        self.sh = np.ascontiguousarray(sh)
        self.validate()

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
        """Raise InputError if any value is non-finite or out of range (scales < 0, opacities outside
        [0, 1], a zero quaternion): exactly what `load_ply` refuses, so a valid set always saves to a
        file that loads. Called on construction and by `save_ply` (the arrays may be edited in place)."""
        n = len(self)
        for name in ("means", "quats", "scales", "opacities", "sh"):
            a = getattr(self, name)
            ok = np.isfinite(a.reshape(n, int(np.prod(a.shape[1:])))).all(axis=1)  # n may be 0
            if not ok.all():
                raise InputError(f"{int(np.count_nonzero(~ok))} Gaussians have non-finite {name} "
                                 f"(first at row {int(np.argmin(ok))})", path)
        for name, bad in (("negative scales", (self.scales < 0).any(axis=1)),
                          ("opacities outside [0, 1]", (self.opacities < 0) | (self.opacities > 1)),
                          ("a zero quaternion", ~self.quats.any(axis=1))):
            if bad.any():
                raise InputError(f"{int(np.count_nonzero(bad))} Gaussians have {name} "
                                 f"(first at row {int(np.argmax(bad))})", path)

    # -- I/O -----------------------------------------------------------------------------------
    def save_ply(self, path: str | Path) -> Path:
        """Write the standard 3DGS PLY (binary little-endian), atomically. The values are validated first
        (InputError, nothing written): a file `load_ply` would refuse is never written."""
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
