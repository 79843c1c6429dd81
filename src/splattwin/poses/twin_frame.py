"""The twin's coordinate frame (`TwinFrame`): where it comes from, whether it is metric, how sure the scale
is. The poses stage defines it (OUT/frame.json); the twin records it in twin.json (`Manifest.frame`).

Not to be confused with `splattwin.capture.Frame`, an image of the capture with its camera.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from splattwin.errors import InputError

FRAME_FILE = "frame.json"

# Where a twin frame can come from (poses stage): see `TwinFrame.source`.
FRAME_SOURCES = ("ground_truth", "known_poses", "robot", "sfm+robot", "marker", "table_plane+known_length", "unscaled")


@dataclass
class TwinFrame:
    """Definition of the twin frame (metres, z up when it comes from the table or the robot base).

    source: one of FRAME_SOURCES. scaled: False when the metric scale is unknown (robot stages refuse).
    scale_uncertainty_rel: 1-sigma relative scale uncertainty (0.01 = 1 %).
    T_twin_input: how the input's coordinates map into the twin frame (e.g. a z-down robot world rotated
    180 degrees about x). up_check: the evidence for up (cameras, table plane) when poses were known.
    """

    source: str = "unscaled"
    scaled: bool = False
    units: str = "m"
    up: str = "+z"
    scale_uncertainty_rel: float | None = None
    description: str = ""
    # [4,4] similarity from the input's world (known or robot poses; the SfM model for SfM) to this frame
    T_twin_input: list | None = None
    # known poses: where up was found and the rotation applied (splattwin.poses.up.UpCheck.to_dict)
    up_check: dict | None = None


def load_frame(path: str | Path) -> TwinFrame:
    """Frame definition from a frame.json (or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / FRAME_FILE
    if not path.is_file():
        raise InputError("no frame definition here (expected frame.json)", path)
    try:
        return TwinFrame(**json.loads(path.read_text()))
    except (json.JSONDecodeError, TypeError) as e:
        raise InputError(f"malformed frame definition: {e}", path) from e
