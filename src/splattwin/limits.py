"""Bounded reads: every size or count read from a file is checked before memory is allocated for it.

A few bytes can claim a 30000x30000 image, a COCO mask of 10^10 pixels, a PLY of 10^12 vertices, a .npy
array of 80 GB, or a YAML document whose nested aliases expand to billions of nodes. The readers here
check the claim against a limit (and, where it applies, against the file's real size) and raise an
InputError naming the file before anything is allocated.

Limits (environment variables override them, e.g. for gigapixel scans):
    SPLATTWIN_MAX_IMAGE_PIXELS   150e6   pixels per image or mask (a 15000x10000 photo)
    SPLATTWIN_MAX_ELEMENTS       100e6   PLY vertices/faces, points, Gaussians
    SPLATTWIN_MAX_JSON_BYTES     1 GiB   JSON files (COCO files of big datasets are hundreds of MB)
    SPLATTWIN_MAX_RECORD_BYTES   64 MiB  small JSON records: twin.json, frame.json, train.json, results
    SPLATTWIN_MAX_YAML_BYTES     16 MiB  YAML files (tasks, robot poses)
    SPLATTWIN_MAX_YAML_NODES     1e6     YAML nodes after expanding aliases
    SPLATTWIN_MAX_TASK_STEPS     100     pick-and-place steps in one task (each is checked by IK and planned)
    SPLATTWIN_MAX_ARRAY_BYTES    16 GiB  .npy arrays (and never more than the file holds)
    SPLATTWIN_MAX_TEXT_BYTES     256 MiB plain-text lists (TUM pose lists, rgb.txt)
    SPLATTWIN_MAX_VIEWS          1e5     views listed by one capture file (transforms.json, cameras.json, BOP)
    SPLATTWIN_MAX_VIDEO_FRAMES   5e5     frames of a video (4.6 h at 30 fps; every frame is decoded to be scored)
"""

from __future__ import annotations

import contextlib
import json
import os
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from splattwin.errors import InputError, short_repr


def _env(name: str, default: float) -> int:
    try:
        return int(float(os.environ.get(name, default)))
    except ValueError:
        return int(default)


MAX_IMAGE_PIXELS = _env("SPLATTWIN_MAX_IMAGE_PIXELS", 150e6)
MAX_ELEMENTS = _env("SPLATTWIN_MAX_ELEMENTS", 100e6)
MAX_JSON_BYTES = _env("SPLATTWIN_MAX_JSON_BYTES", 1 << 30)
# Records the project writes itself (twin.json, frame.json, train.json, pipeline.json, results) are KB to a
# few MB; parsing JSON takes about 10x its size in memory, so the 1 GiB limit meant for COCO files would let
# a received record cost ~10 GB.
MAX_RECORD_BYTES = _env("SPLATTWIN_MAX_RECORD_BYTES", 64 << 20)
MAX_YAML_BYTES = _env("SPLATTWIN_MAX_YAML_BYTES", 16 << 20)
MAX_YAML_NODES = _env("SPLATTWIN_MAX_YAML_NODES", 1e6)
# a task's steps: each is validated with IK and planned (seconds each); a received 16 MiB task of 400 000
# steps ran for hours before any error (the paper's task has 3)
MAX_TASK_STEPS = _env("SPLATTWIN_MAX_TASK_STEPS", 100)
MAX_ARRAY_BYTES = _env("SPLATTWIN_MAX_ARRAY_BYTES", 16 << 30)
MAX_TEXT_BYTES = _env("SPLATTWIN_MAX_TEXT_BYTES", 256 << 20)
# views one capture file may list: its reader spends ~0.1 ms on each and validate() ~3 ms, so the JSON limit
# alone let a received transforms.json of 1.2 M frames (600 MB) or cameras.json of 500 000 run for minutes
MAX_VIEWS = _env("SPLATTWIN_MAX_VIEWS", 100_000)
# frames of a video: its scoring pass decodes every frame (its memory is bounded apart: capture.video.MAX_SCORED),
# and a still scene compresses to ~20 bytes a frame: a few MB can hold hours of frames
MAX_VIDEO_FRAMES = _env("SPLATTWIN_MAX_VIDEO_FRAMES", 500_000)


# -- sizes and counts ---------------------------------------------------------------------------
def check_pixels(width, height, where: str | Path | None = None, what: str = "image") -> tuple[int, int]:
    """(width, height) as ints if both are positive and width*height <= MAX_IMAGE_PIXELS."""
    try:
        if isinstance(width, bool) or isinstance(height, bool):  # int(True) is 1: not a size
            raise TypeError
        w, h = int(width), int(height)
        if w != width or h != height:
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what} size must be whole numbers, got {short_repr(width)} x {short_repr(height)}", where) from None
    if w <= 0 or h <= 0:
        raise InputError(f"{what} size {short_repr(w)}x{short_repr(h)} must be positive", where)
    if w * h > MAX_IMAGE_PIXELS:  # (integer division: a 400-digit size cannot become a float)
        raise InputError(f"{what} claims {short_repr(w)}x{short_repr(h)} = {short_repr(w * h // 10**6)} megapixels, more than the "
                         f"limit of {MAX_IMAGE_PIXELS / 1e6:.0f} (set SPLATTWIN_MAX_IMAGE_PIXELS to allow it)", where)
    return w, h


def check_count(n, where: str | Path | None = None, what: str = "elements", limit: int | None = None,
                setting: str = "SPLATTWIN_MAX_ELEMENTS") -> int:
    """`n` as an int if 0 <= n <= limit (default MAX_ELEMENTS); `setting`: the variable the error says raises it."""
    limit = MAX_ELEMENTS if limit is None else limit
    try:
        k = int(n)
        if k != n:
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"count of {what} must be a whole number, got {n!r}", where) from None
    if k < 0 or k > limit:
        raise InputError(f"{k} {what} is outside [0, {limit}] (set {setting} to allow more)", where)
    return k


def check_file_size(path: str | Path, limit: int, what: str = "file") -> int:
    """The file's size in bytes; InputError if it is missing or larger than `limit`."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as e:
        raise InputError(f"{what} cannot be read ({e.strerror or e})", path) from None
    if size > limit:
        raise InputError(f"{what} is {size_text(size)}, more than the limit of {size_text(limit)}", path)
    return size


def size_text(n_bytes: int) -> str:
    """A byte count for a message: "512 bytes", "3.4 KiB", "1.5 MiB", "2.0 GiB" (one decimal, so a size just
    over a limit does not read as equal to it)."""
    n = float(n_bytes)
    if n < 1024:
        return f"{int(n)} bytes"
    for unit in ("KiB", "MiB", "GiB"):
        n /= 1024
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}"
    raise AssertionError("unreachable")


# -- numbers read from files --------------------------------------------------------------------
# Camera positions and translations read from a capture, metres: beyond Earth-centred coordinates
# (6.4e6 m), so a georeferenced capture (UTM, ECEF) passes, and it keeps squares and products of
# coordinates (plane fits, SVDs) finite: 1e308 m overflowed there and LAPACK never returned. (A twin's
# own coordinates, in its table frame, have the tighter splattwin.twin.manifest.MAX_LENGTH.)
MAX_POSITION = 1e9


def ascii_uint(text, max_digits: int = 18) -> int | None:
    """`text` as an int when it is 1 to max_digits ASCII digits (an id or key read from a file), else None.
    str.isdigit() alone also passes '²' or Arabic-Indic digits, which int() then refuses or reads."""
    if isinstance(text, str) and 0 < len(text) <= max_digits and text.isascii() and text.isdigit():
        return int(text)
    return None


def number(v, where: str | Path | None = None, what: str = "value", low: float = -np.inf,
           high: float = np.inf) -> float:
    """`v` (a value parsed from JSON or YAML) as a finite float in [low, high], else InputError naming
    `where`. Only real numbers count: not bools (True is 1 to Python), not text ("153.75"; JSON and YAML
    have numbers of their own), not integers beyond float range."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        hint = ""
        if isinstance(v, str):
            try:
                float(v)
                hint = (" (write numbers without quotes; YAML (PyYAML) reads an exponent without a decimal point and "
                        "a sign, like 1e3 or 1.0e3, as text: write 1.0e+3)")
            except ValueError:
                pass
        raise InputError(f"{what} must be a number, got {type(v).__name__} {short_repr(v)}{hint}", where)
    try:
        x = float(v)
    except OverflowError:
        raise InputError(f"{what} {short_repr(v)} is too large", where) from None
    if not np.isfinite(x):
        raise InputError(f"{what} must be a finite number, got non-finite {x}", where)
    if not low <= x <= high:
        raise InputError(f"{what} must be within [{low:g}, {high:g}], got {x:g}", where)
    return x


def numbers(v, n: int, where: str | Path | None = None, what: str = "values", low: float = -np.inf,
            high: float = np.inf) -> np.ndarray:
    """`v` (a list of n numbers, or nested lists holding n, e.g. a 3x3 matrix) as a flat float64 array [n],
    each checked by `number`."""
    if not isinstance(v, (list, tuple)):
        raise InputError(f"{what} must be a list of {n} numbers, got {type(v).__name__} {short_repr(v)}", where)
    flat: list = []
    stack, pushed = [v], 0
    while stack:
        x = stack.pop()
        if isinstance(x, (list, tuple)):
            pushed += len(x)
            if pushed > 4 * n + 4:  # bounded work on a huge or deeply nested list
                raise InputError(f"{what} must hold {n} numbers", where)
            stack.extend(reversed(x))
        else:
            flat.append(x)
    if len(flat) != n:
        raise InputError(f"{what} must hold {n} numbers, got {len(flat)}", where)
    return np.array([number(x, where, f"{what} element {i + 1}", low, high) for i, x in enumerate(flat)])


# -- PLY ------------------------------------------------------------------------------------------
_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def check_ply_header(path: str | Path, what: str = "PLY file", max_header: int = 1 << 16) -> dict[str, int]:
    """Element counts of a PLY file's header ({"vertex": n, "face": m, ...}), each checked against
    MAX_ELEMENTS and, for binary files of fixed-size elements, against the bytes the file really holds,
    before a library allocates arrays for them."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} does not exist", path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(max_header)
    if not head.startswith(b"ply"):
        raise InputError(f"not a {what} (missing 'ply' magic)", path)
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(f"{what} header has no 'end_header' in its first {max_header} bytes", path)
    body = head.find(b"\n", end) + 1
    counts: dict[str, int] = {}
    fixed = True
    row_bytes: dict[str, int] = {}
    binary = False
    current = None
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            binary = len(tok) > 1 and tok[1].startswith("binary")
        elif tok[0] == "element" and len(tok) == 3:
            current = tok[1]
            counts[current] = check_count(tok[2] if not tok[2].isdigit() else int(tok[2]), path,
                                          f"'{current}' elements in the {what} header")
            row_bytes[current] = 0
        elif tok[0] == "property" and current is not None:
            if len(tok) > 1 and tok[1] == "list":
                fixed = False
            elif len(tok) == 3 and tok[1] in _PLY_SIZES:
                row_bytes[current] += _PLY_SIZES[tok[1]]
    if binary and fixed and body > 0:
        need = sum(counts[e] * row_bytes[e] for e in counts)
        if need > size - body:
            raise InputError(f"{what} header claims {need} bytes of data but the file holds {size - body}", path)
    return counts


# -- images -------------------------------------------------------------------------------------
def _register_heif(path: Path) -> None:
    """Teach PIL to read HEIC/HEIF (an iPhone's default photo format) through pillow-heif, once. libheif
    applies the rotation the container records (a portrait shot's), so the pixels come out upright."""
    try:
        import pillow_heif
    except ImportError:
        raise InputError("HEIC/HEIF photos need the pillow-heif package (pip install pillow-heif), or convert "
                         "them to JPEG first", path) from None
    if not getattr(_register_heif, "done", False):
        pillow_heif.register_heif_opener()
        _register_heif.done = True


@contextlib.contextmanager
def open_image(path: str | Path, what: str = "image") -> Iterator[Any]:
    """PIL image opened lazily (header only) whose size was checked against MAX_IMAGE_PIXELS; decode
    it with `im.load()` / `np.asarray(im)` inside the block. InputError for missing, unreadable or
    oversized files."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file does not exist", path)
    if path.suffix.lower() in (".heic", ".heif"):
        _register_heif(path)
    with warnings.catch_warnings():
        # PIL's own bomb guard warns above 89 MP and raises above 179 MP; ours is the limit that counts.
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            im = Image.open(path)
        except Image.DecompressionBombError as e:
            raise InputError(f"{what} claims more than the limit of {MAX_IMAGE_PIXELS / 1e6:.0f} megapixels "
                             f"(PIL: {e})", path) from None
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
            raise InputError(f"unreadable {what} ({e.__class__.__name__}: {e})", path) from None
        try:
            check_pixels(*im.size, where=path, what=what)
            yield im
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:  # decoding a corrupt body
            raise InputError(f"unreadable {what} ({e.__class__.__name__}: {e})", path) from None
        finally:
            im.close()


def image_size(path: str | Path, what: str = "image") -> tuple[int, int]:
    """(width, height) from the header, checked against the pixel limit."""
    with open_image(path, what) as im:
        return im.size


_JPEG_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif")
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"   # the IEND chunk (length 0, type, CRC) every PNG ends with


def check_image_complete(path: str | Path, what: str = "image") -> None:
    """InputError naming `path` if the image is truncated or its data is corrupt (a copy cut short, a
    half-synced upload), so a capture fails before SfM rather than at training time.

    Cheap for the usual files: a JPEG that ends with its EOI marker (FF D9) or a PNG that ends with its
    IEND chunk is complete; only the last bytes are read. A cut-short file cannot end with them (inside
    JPEG entropy-coded data an FF byte is always followed by 00 or a restart marker). Anything else (data
    after the end marker, e.g. a phone's motion photo with its video appended; other formats) is decoded
    to decide: a JPEG at 1/8 scale (`draft`), which still reads every coefficient, so truncation is
    caught at a fraction of a full decode (measured on a 12 MP JPEG: 40 ms instead of 80 ms); other formats in full.
    PIL's `verify()` is no substitute: for a JPEG it checks nothing past the header."""
    path = Path(path)
    suffix = path.suffix.lower()
    end = _PNG_END if suffix == ".png" else b"\xff\xd9" if suffix in _JPEG_SUFFIXES else None
    if end is not None:
        try:
            with open(path, "rb") as f:
                f.seek(0, os.SEEK_END)
                size = f.tell()
                f.seek(max(size - len(end), 0))
                if f.read() == end:
                    return
        except OSError as e:
            raise InputError(f"{what} cannot be read ({e.strerror or e})", path) from None
    with open_image(path, what) as im:
        if suffix in _JPEG_SUFFIXES:
            im.draft(im.mode, (max(im.width // 8, 1), max(im.height // 8, 1)))
        try:
            im.load()
        except (OSError, ValueError, SyntaxError, EOFError) as e:
            raise InputError(f"{what} is truncated or corrupt (PIL: {e}): the file was cut short or damaged (an "
                             f"interrupted copy or download?); copy it again or leave it out", path) from None


# PIL modes of 16-bit (and 32-bit integer) greyscale images: machine-vision and ROS "mono16" frames
_HIGH_BIT_GREY = ("I;16", "I;16B", "I;16L", "I;16N", "I")


def read_image_array(path: str | Path, mode: str | None = None, what: str = "image") -> np.ndarray:
    """Decoded image as a numpy array (optionally converted to a PIL mode such as "RGB").

    A 16-bit greyscale image converted to "RGB" or "L" is scaled from its 0..65535 range to 8 bits (PIL's
    own conversion clips it: every pixel of a 16-bit photo above 255 became white, and training on such a
    capture reported 12 dB without a word); a 32-bit float image is no photo and is refused."""
    with open_image(path, what) as im:
        im.load()
        if mode in ("RGB", "L") and im.mode in _HIGH_BIT_GREY:
            a = np.asarray(im)
            if a.size and (int(a.min()) < 0 or int(a.max()) > 65535):
                raise InputError(f"{what}: 32-bit integer pixel values outside 0..65535 ({im.mode}); save it as an "
                                 f"8- or 16-bit image", path)
            g8 = ((a.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
            return np.repeat(g8[..., None], 3, axis=2) if mode == "RGB" else g8
        if mode in ("RGB", "L") and im.mode == "F":
            raise InputError(f"{what}: a 32-bit float image (a depth or data map?), not a photo", path)
        return np.asarray(im.convert(mode) if mode is not None and im.mode != mode else im)


# -- arrays -------------------------------------------------------------------------------------
def load_npy(path: str | Path, what: str = "array", max_bytes: int | None = None) -> np.ndarray:
    """A .npy array (never pickles) whose header was checked: shape x itemsize must fit in the file
    and under `max_bytes` (default MAX_ARRAY_BYTES) before the data is read."""
    path = Path(path)
    limit = MAX_ARRAY_BYTES if max_bytes is None else max_bytes
    if not path.is_file():
        raise InputError(f"{what} file does not exist", path)
    size = path.stat().st_size
    try:
        with open(path, "rb") as f:
            shape, dtype = npy_header(f)
            if dtype.hasobject:
                raise InputError(f"{what} holds Python objects (pickles); only plain numeric arrays are read", path)
            need = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if need > limit or need > size - f.tell():
                raise InputError(f"{what} header claims shape {tuple(shape)} ({need / 2**20:.1f} MiB) but the file "
                                 f"holds {max(size - f.tell(), 0) / 2**20:.1f} MiB of data (limit "
                                 f"{limit / 2**20:.0f} MiB)", path)
            f.seek(0)
            return np.load(f, allow_pickle=False)
    except InputError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise InputError(f"not a readable .npy {what}: {e}", path) from None


def npy_header(f) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from the header of an .npy stream; only the header bytes are read."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
    elif version in ((2, 0), (3, 0)):
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise ValueError(f"unsupported .npy version {version}")
    return tuple(int(n) for n in shape), dtype


MAX_NPZ_MEMBERS = 100_000   # arrays in one .npz (a robot playback track holds two per robot geom)


def load_npz(path: str | Path, what: str = "array archive", max_bytes: int | None = None,
             check: Callable[[dict], str | None] | None = None) -> dict[str, np.ndarray]:
    """All arrays of an .npz without unpickling, every size bounded before anything is inflated.

    A 20 MB zip can declare gigabytes of zeros, so the zip directory's uncompressed sizes are summed
    against `max_bytes` (default MAX_ARRAY_BYTES) and every member's .npy header (shape, dtype) is read
    and must fit its member; then `check(headers)` ({name: (shape, dtype)}) may refuse the shapes (return
    a message) before any array data is read. Arrays are read straight from the zip stream into their
    final buffer (no second copy of a member in memory)."""
    import zipfile

    path = Path(path)
    limit = MAX_ARRAY_BYTES if max_bytes is None else max_bytes
    headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            members = [i for i in zf.infolist() if i.filename.endswith(".npy")]
            if len(members) > MAX_NPZ_MEMBERS:
                raise InputError(f"{what} holds {len(members)} arrays, more than {MAX_NPZ_MEMBERS}", path)
            total = sum(i.file_size for i in members)
            if total > limit:
                raise InputError(f"{what}: arrays of {total} bytes uncompressed are larger than the limit "
                                 f"({limit})", path)
            for info in members:
                name = info.filename[:-4]
                if name in headers:
                    raise InputError(f"{what} holds the array {name!r} twice", path)
                with zf.open(info) as f:
                    shape, dtype = npy_header(f)
                if dtype.hasobject:
                    raise InputError(f"{what} array {name!r} holds Python objects (pickles); only plain arrays "
                                     f"are read", path)
                need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if need > info.file_size:
                    raise InputError(f"{what} array {name!r} claims shape {tuple(shape)} but its member holds "
                                     f"{info.file_size} bytes", path)
                headers[name] = (tuple(shape), dtype)
            problem = check(headers) if check is not None else None
            if problem:
                raise InputError(f"{what}: {problem}", path)
            for info in members:
                with zf.open(info) as f:
                    out[info.filename[:-4]] = np.lib.format.read_array(f, allow_pickle=False)
    except InputError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, NotImplementedError) as e:
        raise InputError(f"not a readable .npz {what}: {e}", path) from None
    return out


# -- text ----------------------------------------------------------------------------------------
def read_text(path: str | Path, what: str = "text file", max_bytes: int | None = None) -> str:
    """A UTF-8 text file of at most `max_bytes` (default MAX_TEXT_BYTES); InputError naming the file
    when it is missing, too large or not UTF-8."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} does not exist", path)
    check_file_size(path, MAX_TEXT_BYTES if max_bytes is None else max_bytes, what)
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{what} is not UTF-8 text: {e}", path) from None


# -- JSON and YAML ------------------------------------------------------------------------------
def read_json(path: str | Path, missing: str = "file not found", max_bytes: int | None = None) -> Any:
    """Parse a JSON file of at most `max_bytes` (default MAX_JSON_BYTES); InputError naming the file
    when it is missing, too large, too deeply nested or not valid JSON."""
    path = Path(path)
    if not path.is_file():
        raise InputError(missing, path)
    check_file_size(path, MAX_JSON_BYTES if max_bytes is None else max_bytes, "JSON file")
    try:
        data = json.loads(path.read_bytes(), object_pairs_hook=_unique_keys)
    except RecursionError:
        raise InputError("JSON is nested too deeply", path) from None
    except _DuplicateKey as e:
        raise InputError(f"JSON object has the key {short_repr(e.key)} twice (which one is meant?)", path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"not valid JSON: {e}", path) from None
    except ValueError as e:  # Python refuses integers of more than 4300 digits (sys.get_int_max_str_digits)
        raise InputError(f"JSON holds a number too long to read ({str(e).split(';')[0]})", path) from None
    if max_bytes is not None and max_bytes <= MAX_RECORD_BYTES and not _nested_within(data, MAX_RECORD_DEPTH):
        raise InputError(f"JSON is nested more than {MAX_RECORD_DEPTH} levels deep (not a record splattwin wrote)",
                         path)
    return data


# Records (read within MAX_RECORD_BYTES) are often written back (pipeline.json, refined poses): json.loads takes up
# to ~990 levels, but writing such a document again recursed past Python's limit (RecursionError). The project's
# own records nest a few levels.
MAX_RECORD_DEPTH = 100


def _nested_within(obj: Any, limit: int) -> bool:
    """True if lists and objects in `obj` nest at most `limit` levels (iterative: no recursion of its own)."""
    stack = [(obj, 1)]
    while stack:
        o, depth = stack.pop()
        children = o.values() if isinstance(o, dict) else o if isinstance(o, list) else ()
        if children and depth > limit:
            return False
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))
    return True


class _DuplicateKey(ValueError):
    def __init__(self, key: str):
        super().__init__(key)
        self.key = key


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    """json object_pairs_hook: a key given twice is refused (json keeps the last one silently, so two
    entries for one image would hide one). As fast as the default (measured on a 72 MB COCO file)."""
    d = dict(pairs)
    if len(d) != len(pairs):
        seen: set[str] = set()
        raise _DuplicateKey(next(k for k, _ in pairs if k in seen or seen.add(k)))
    return d


OPENCV_MATRIX_TAG = "tag:yaml.org,2002:opencv-matrix"   # cv::FileStorage's `!!opencv-matrix`


def _yaml_loader(max_nodes: int, where: Path | None, opencv: bool = False):
    import yaml

    class BoundedLoader(yaml.SafeLoader):
        """yaml.SafeLoader that refuses documents whose aliases expand to more than `max_nodes` nodes
        (the "billion laughs" bomb) or that refer to themselves."""

        def compose_document(self):
            node = super().compose_document()
            _check_expanded_size(node, max_nodes, where)
            return node

        def construct_mapping(self, node, deep=False):
            # a key given twice is refused, as in JSON (YAML's loaders keep the last one silently); keys
            # brought in by a merge (<<: *base) may be overridden, as YAML intends
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    if key in seen:
                        raise InputError(f"YAML key {short_repr(key)} is given twice "
                                         f"(line {key_node.start_mark.line + 1})", where)
                    seen.add(key)
                except TypeError:  # an unhashable key: the constructor below refuses it
                    break
            return super().construct_mapping(node, deep)

    if opencv:
        # OpenCV FileStorage / ORB-SLAM files tag matrices `!!opencv-matrix` (rows, cols, dt, data): read
        # as the plain mapping it is; the node bounds above still apply
        def _opencv_matrix(loader, node):
            if not isinstance(node, yaml.MappingNode):
                raise InputError(f"!!opencv-matrix on line {node.start_mark.line + 1} must be a mapping "
                                 f"(rows, cols, dt, data)", where)
            return loader.construct_mapping(node, deep=True)

        BoundedLoader.add_constructor(OPENCV_MATRIX_TAG, _opencv_matrix)
    return BoundedLoader


def _check_expanded_size(root, max_nodes: int, where: Path | None) -> None:
    """Nodes of the document with every alias expanded, counted on the shared graph in linear time."""
    import yaml

    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            on_path.discard(key)
            if isinstance(node, yaml.SequenceNode):
                children = node.value
            elif isinstance(node, yaml.MappingNode):
                children = [x for kv in node.value for x in kv]
            else:
                children = []
            total = 1 + sum(size[id(c)] for c in children)
            if total > max_nodes:
                raise InputError(f"YAML expands to more than {max_nodes} nodes through its aliases (&anchor / "
                                 f"*alias); refusing to load it", where)
            size[key] = total
            continue
        if key in size:
            continue
        if key in on_path:
            raise InputError("YAML alias refers to a node that contains it (a recursive structure)", where)
        on_path.add(key)
        stack.append((node, True))
        if isinstance(node, yaml.SequenceNode):
            stack.extend((c, False) for c in node.value if id(c) not in size)
        elif isinstance(node, yaml.MappingNode):
            stack.extend((c, False) for kv in node.value for c in kv if id(c) not in size)


def load_yaml(path: str | Path, max_bytes: int | None = None, max_nodes: int | None = None) -> Any:
    """Parse a YAML file safely (plain data only, `yaml.SafeLoader`) with bounded size and aliases."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError("file does not exist", path)
    check_file_size(path, MAX_YAML_BYTES if max_bytes is None else max_bytes, "YAML file")
    return loads_yaml(path.read_bytes(), path, max_nodes)


def loads_yaml(text: str | bytes, where: str | Path | None = None, max_nodes: int | None = None,
               opencv: bool = False) -> Any:
    """`load_yaml` for text already in memory (`where` is named in errors). opencv: also read OpenCV
    FileStorage's `!!opencv-matrix` tag, as a plain mapping {rows, cols, dt, data}."""
    import yaml

    loader = _yaml_loader(MAX_YAML_NODES if max_nodes is None else max_nodes, where, opencv)
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise InputError("YAML is nested too deeply", where) from None
    except yaml.YAMLError as e:
        raise InputError(f"not valid YAML: {e}", where) from None
    except UnicodeDecodeError as e:
        raise InputError(f"YAML is not valid UTF-8 text: {e}", where) from None
    except ValueError as e:  # Python refuses integers of more than 4300 digits (sys.get_int_max_str_digits)
        raise InputError(f"YAML holds a number too long to read ({str(e).split(';')[0]})", where) from None
