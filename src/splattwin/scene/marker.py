"""ArUco fiducial printed flat on the table (OpenCV `cv2.aruco`, DICT_4X4_50).

Marker frame = OpenCV's convention for `solvePnP` / `estimatePoseSingleMarkers`: origin at the marker
centre, x to the right of the printed image, y up the image, z out of the table; corners in the order
top-left (-s/2, s/2), top-right, bottom-right, bottom-left. `size` is the side of the outer black square
(metres); a white quiet zone one module wide surrounds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from splattwin.transforms import pose_xyz_yaw

DICTIONARY = "DICT_4X4_50"
_BITS = 4  # data bits per side; +2 border modules


@dataclass(frozen=True)
class TableMarker:
    """A marker lying on the table (z = 0) at (x, y) with yaw about world z. Units metres, radians."""

    marker_id: int
    size: float
    x: float
    y: float
    yaw: float

    @property
    def T_world_marker(self) -> np.ndarray:
        return pose_xyz_yaw(self.x, self.y, 0.0, self.yaw)

    def bitmap(self) -> np.ndarray:
        """Marker image, one pixel per module, border included. -> [6,6] uint8 {0,255}"""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
        return cv2.aruco.generateImageMarker(d, self.marker_id, _BITS + 2, borderBits=1)

    def corners_world(self) -> np.ndarray:
        """Outer corners in OpenCV order (TL, TR, BR, BL). -> [4,3] world metres"""
        h = self.size / 2
        local = np.array([[-h, h, 0, 1], [h, h, 0, 1], [h, -h, 0, 1], [-h, -h, 0, 1]])
        return (local @ self.T_world_marker.T)[:, :3]

    def texture(self):
        """`f(p_world [N,3]) -> [N]`: 1 white / 0 black inside the marker + quiet zone, nan elsewhere."""
        bm = self.bitmap() > 127
        n = bm.shape[0]
        module = self.size / n
        Tinv = np.linalg.inv(self.T_world_marker)

        def f(p: np.ndarray) -> np.ndarray:
            q = np.einsum("ij,kj->ik", p, Tinv[:3, :3]) + Tinv[:3, 3]
            out = np.full(len(p), np.nan, dtype=np.float32)
            quiet = (np.abs(q[:, 0]) < self.size / 2 + module) & (np.abs(q[:, 1]) < self.size / 2 + module) \
                & (np.abs(q[:, 2]) < 1e-3)
            out[quiet] = 1.0
            col = np.floor((q[:, 0] + self.size / 2) / module).astype(np.int64)
            row = np.floor((self.size / 2 - q[:, 1]) / module).astype(np.int64)
            inside = quiet & (col >= 0) & (col < n) & (row >= 0) & (row < n)
            out[inside] = bm[row[inside], col[inside]].astype(np.float32)
            return out

        return f

    def to_json(self) -> dict:
        return {"id": self.marker_id, "dictionary": DICTIONARY, "size": self.size,
                "T_world_marker": self.T_world_marker.tolist(), "corners_world": self.corners_world().tolist()}
