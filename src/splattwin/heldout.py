"""The default hold-out rule, for a capture without a train/held-out split of its own: every 8th view from
the first when there are at least 6 views (Mip-NeRF 360 / 3DGS convention: views 0, 8, 16, ...), none
below 6. Shared (no stage imports it from another) so that `capture info` reports the split `poses`,
`train` and `build` will use; `splattwin.poses.holdout` applies it, with the options that override it."""

from __future__ import annotations

from splattwin.wording import ordinal

HELDOUT_EVERY_DEFAULT = 8   # Mip-NeRF 360 / 3DGS: every 8th view, starting with the first
HELDOUT_MIN_VIEWS = 6       # below this many views nothing is held out by default


def default_heldout(n: int) -> tuple[list[int], int | None, str]:
    """(held-out positions among n views in capture order, the K of every K-th or None, the rule in words)."""
    if n >= HELDOUT_MIN_VIEWS:
        every = HELDOUT_EVERY_DEFAULT
        return (list(range(0, n, every)), every,
                f"every {ordinal(every)} view from the first (default with >= {HELDOUT_MIN_VIEWS} views)")
    return [], None, f"none (fewer than {HELDOUT_MIN_VIEWS} views)"
