"""COCO run-length encoding of binary masks (the `{"size": [h, w], "counts": ...}` objects of COCO JSON).

pycocotools is not a dependency (it needs a C build and pulls matplotlib), so the two small codecs are
written here, following the COCO mask API format exactly:
- runs are taken over the mask flattened in column-major (Fortran) order, starting with a run of zeros
  (possibly of length 0), alternating 0/1;
- "uncompressed" RLE stores the run lengths as a list of ints;
- "compressed" RLE stores them as an ASCII string: each count (from the third on, the difference to the
  count two places earlier) is written as a little-endian sequence of 5-bit groups, char = group + 48,
  with bit 0x20 set on every group but the last and the sign carried in bit 0x10 of the last group.
"""

from __future__ import annotations

import numpy as np

from splattwin.errors import InputError


def mask_to_counts(mask: np.ndarray) -> list[int]:
    """Binary mask [H,W] -> run lengths (column-major, starting with zeros)."""
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    if flat.size == 0:
        return [0]
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    runs = np.diff(bounds).tolist()
    if flat[0]:  # COCO runs always start with a (possibly empty) zero run
        runs = [0] + runs
    return [int(r) for r in runs]


def counts_to_mask(counts: list[int], height: int, width: int) -> np.ndarray:
    """Run lengths -> bool mask [H,W]. Raises InputError when the runs do not cover H*W pixels or the
    size is beyond `splattwin.limits.MAX_IMAGE_PIXELS` (checked before anything is allocated)."""
    from splattwin.limits import check_pixels

    width, height = check_pixels(width, height, None, "RLE mask")
    n = height * width
    if isinstance(counts, np.ndarray):
        counts = counts.tolist()
    if not isinstance(counts, (list, tuple)):
        raise InputError(f"RLE counts must be a list of run lengths, got {type(counts).__name__}")
    # a valid encoding has at most one run per pixel plus the leading zero run
    if len(counts) > n + 1:
        raise InputError(f"RLE has {len(counts)} runs but the mask has only {height}x{width}={n} pixels")
    # checked as Python ints before numpy: int64 sums wrap (2**63-1 twice + k "sums" to H*W) and np.repeat
    # of such counts writes out of bounds
    for i, c in enumerate(counts):
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)):
            raise InputError(f"RLE counts must be whole numbers, got {str(c)[:40]!r} at run {i}")
        if c < 0:
            raise InputError(f"RLE count {i} is negative ({c}): run lengths are pixel counts")
    total = sum(int(c) for c in counts)
    if total != n:
        raise InputError(f"RLE counts sum to {total} but the mask has {height}x{width}={n} pixels")
    counts = np.asarray(counts, dtype=np.int64)  # each now in [0, H*W]
    values = (np.arange(counts.size) % 2).astype(bool)
    flat = np.repeat(values, counts)
    return flat.reshape((height, width), order="F")


def counts_to_string(counts: list[int]) -> str:
    """Run lengths -> COCO compressed RLE string (LEB128-like 5-bit groups, delta from two runs back)."""
    out: list[str] = []
    for i, c in enumerate(counts):
        x = int(c) - (int(counts[i - 2]) if i > 2 else 0)
        more = True
        while more:
            g = x & 0x1F
            x >>= 5  # arithmetic shift: negative deltas end at -1
            more = (x != -1) if (g & 0x10) else (x != 0)
            if more:
                g |= 0x20
            out.append(chr(g + 48))
    return "".join(out)


# 5-bit groups per count: 13 hold any 64-bit value, so a longer count is nonsense, and bounding the groups
# keeps decoding linear (an unbounded "____...0" count builds one huge int, quadratically)
_MAX_GROUPS = 13


def string_to_counts(s: str, n_pixels: int | None = None) -> list[int]:
    """COCO compressed RLE string -> run lengths. With `n_pixels` (H*W of the mask) every count must lie
    in [0, n_pixels] and there may be at most n_pixels + 1 of them (checked while decoding)."""
    counts: list[int] = []
    p = 0
    n = len(s)
    if n_pixels is not None and n > _MAX_GROUPS * (n_pixels + 1):
        raise InputError(f"COCO RLE string of {n} characters is too long for a mask of {n_pixels} pixels")
    while p < n:
        x = 0
        k = 0
        more = True
        while more:
            if p >= n:
                raise InputError(f"truncated COCO RLE string {s[:40]!r}")
            if k >= _MAX_GROUPS:
                raise InputError(f"COCO RLE string holds a run length of more than {_MAX_GROUPS} characters "
                                 f"(at character {p}): not a pixel count")
            g = ord(s[p]) - 48
            if g < 0 or g > 63:
                raise InputError(f"invalid character {s[p]!r} in COCO RLE string")
            x |= (g & 0x1F) << (5 * k)
            more = bool(g & 0x20)
            p += 1
            k += 1
            if not more and (g & 0x10):
                x |= -1 << (5 * k)
        if len(counts) > 2:
            x += counts[-2]
        if n_pixels is not None:
            if not 0 <= x <= n_pixels:
                raise InputError(f"COCO RLE run {len(counts)} has length {x}, outside [0, {n_pixels}] "
                                 f"(the mask's pixels)")
            if len(counts) > n_pixels:
                raise InputError(f"COCO RLE string has more runs than the mask's {n_pixels} pixels")
        counts.append(x)
    return counts


def encode(mask: np.ndarray, compressed: bool = True) -> dict:
    """Bool mask [H,W] -> COCO RLE dict {"size": [H, W], "counts": str | list[int]}."""
    mask = np.asarray(mask)
    counts = mask_to_counts(mask)
    return {"size": [int(mask.shape[0]), int(mask.shape[1])],
            "counts": counts_to_string(counts) if compressed else counts}


def decode(rle: dict) -> np.ndarray:
    """COCO RLE dict (compressed string or uncompressed list counts) -> bool mask [H,W]."""
    from splattwin.limits import check_pixels

    try:
        size, counts = rle["size"], rle["counts"]
        h, w = size
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"malformed COCO RLE (need size [h, w] and counts): {e}") from e
    w, h = check_pixels(w, h, None, "RLE mask")
    if isinstance(counts, bytes):
        try:
            counts = counts.decode("ascii")
        except UnicodeDecodeError:
            raise InputError("COCO RLE string is not ASCII") from None
    if isinstance(counts, str):
        counts = string_to_counts(counts, h * w)
    return counts_to_mask(counts, h, w)
