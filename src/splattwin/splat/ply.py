"""The standard 3D Gaussian Splatting PLY format (Kerbl et al. 2023), read and written.

Vertex properties, in this order, float32, binary little-endian when we write:
    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3(K-1)-1)  opacity  scale_0..2  rot_0..3
with opacity a logit, scales natural logs, rot a wxyz quaternion (not necessarily normalised), and
f_rest stored channel-major (all K-1 coefficients of R, then G, then B), as the original code's
`features_rest.transpose(1, 2).flatten(1)` does. SuperSplat, gsplat, nerfstudio and the Unity plug-in
read exactly this.

The reader is our own (numpy only, no plyfile dependency) because it must accept other tools' variants
-- ascii or binary (either endianness), float or double, any order of properties, extra properties
(ignored), any SH degree (inferred from the f_rest count), extra elements -- and turn every malformed
file into an `InputError` naming the file and the problem.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.io import atomic_path
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0, sh_degree_from_bases

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_REQUIRED = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


# -- writing ------------------------------------------------------------------------------------
def property_names(sh_degree: int) -> list[str]:
    """Vertex property names of the standard layout for a given SH degree."""
    k_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(k_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-12, 1.0 - 1e-12)  # float64: keeps finite logits for saturated opacities
    return np.log(p) - np.log1p(-p)


def _storable_quats(q: np.ndarray) -> np.ndarray:
    """`q` [N, 4] with the rows float32 cannot hold -- all zero (every component below float32's smallest
    subnormal, e.g. [1e-50, 0, 0, 0]: `load_ply` would refuse the zero quaternion) or non-finite (beyond
    float32's range) -- normalised: the same rotation (the reader normalises). Every other row is kept as
    given, so the files of valid quaternions stay bit-identical."""
    with np.errstate(over="ignore", under="ignore"):
        q32 = q.astype(np.float32)
    fix = ~q32.any(axis=1) | ~np.isfinite(q32).all(axis=1)
    if not fix.any():
        return q
    q = q.copy()
    r = q[fix] / np.abs(q[fix]).max(axis=1, keepdims=True)  # max |q| > 0 (validate): no under/overflow
    q[fix] = r / np.linalg.norm(r, axis=1, keepdims=True)
    return q


def gaussians_to_array(g: Gaussians) -> np.ndarray:
    """[N, P] float32 rows in the standard property order."""
    n, k = len(g), g.sh.shape[1]
    rest = np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(n, 3 * (k - 1))  # channel-major
    with np.errstate(divide="ignore"):
        log_scales = np.log(g.scales)
    cols = [g.means, np.zeros((n, 3)), g.sh[:, 0, :], rest, _logit(g.opacities)[:, None],
            np.maximum(log_scales, -1e30), _storable_quats(g.quats)]
    with np.errstate(over="ignore"):  # beyond float32's range -> inf, refused by the writer
        return np.concatenate(cols, axis=1).astype("<f4")


def write_gaussians_ply(path: str | Path, g: Gaussians, comments=()) -> Path:
    """Write `g` as a binary little-endian 3DGS PLY, atomically. comments: extra `comment` header lines
    (e.g. the units and frame); each is made one line of printable ASCII (the header is ASCII)."""
    path = Path(path)
    g.validate(path)  # never write a file that `read_gaussians_ply` refuses
    names = property_names(g.sh_degree)
    extra = [" ".join(str(c).encode("ascii", "replace").decode("ascii").split()) for c in comments]
    header = ["ply", "format binary_little_endian 1.0", "comment written by splattwin",
              *(f"comment {c}" for c in extra if c), f"element vertex {len(g)}"]
    header += [f"property float {n}" for n in names]
    header += ["end_header"]
    data = gaussians_to_array(g)
    assert data.shape[1] == len(names)
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():  # finite float64 beyond float32's range (~3.4e38) would be stored as inf
        raise InputError(f"{int(bad.sum())} Gaussians have values beyond float32's range, which the PLY "
                         f"stores (first at row {int(np.argmax(bad))}); not written", path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
    return path


# -- reading ------------------------------------------------------------------------------------
class _Element:
    def __init__(self, name: str, count: int):
        self.name, self.count = name, count
        self.props: list[tuple[str, str]] = []  # (name, numpy type code)
        self.has_list = False


def _parse_header(raw: bytes, path: Path) -> tuple[str, list[_Element], int]:
    """Return (format, elements, byte offset of the body)."""
    if not raw.startswith(b"ply"):
        raise InputError("not a PLY file (missing 'ply' magic)", path)
    end = raw.find(b"end_header")
    if end < 0:
        raise InputError("PLY header has no 'end_header'", path)
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise InputError("PLY header is truncated", path)
    body = nl + 1
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError("PLY header is not ASCII", path) from None
    fmt = None
    elements: list[_Element] = []
    for ln, line in enumerate(lines[1:], start=2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise InputError(f"PLY header line {ln}: unknown format {line!r}", path)
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise InputError(f"PLY header line {ln}: bad element line {line!r}", path)
            elements.append(_Element(tok[1], int(tok[2])))
        elif tok[0] == "property":
            if not elements:
                raise InputError(f"PLY header line {ln}: property before any element", path)
            if len(tok) >= 2 and tok[1] == "list":
                prop = (tok[-1], "list")
                elements[-1].has_list = True
            elif len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise InputError(f"PLY header line {ln}: bad property {line!r}", path)
            else:
                prop = (tok[2], _PLY_TYPES[tok[1]])
            if any(prop[0] == name for name, _ in elements[-1].props):
                raise InputError(f"PLY header line {ln}: element {elements[-1].name[:40]!r} has property "
                                 f"{prop[0][:40]!r} twice", path)
            elements[-1].props.append(prop)
        else:
            raise InputError(f"PLY header line {ln}: unexpected keyword {tok[0]!r}", path)
    if fmt is None:
        raise InputError("PLY header has no 'format' line", path)
    return fmt, elements, body


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """All vertex properties of a PLY file as float64 arrays [N], keyed by property name."""
    path = Path(path)
    if not path.is_file():
        raise InputError("PLY file not found", path)
    raw = path.read_bytes()
    fmt, elements, body = _parse_header(raw, path)
    from splattwin.limits import check_count

    for e in elements:
        check_count(e.count, path, f"'{e.name}' elements")
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError("PLY has no 'vertex' element", path)
    vi = names.index("vertex")
    vert = elements[vi]
    if vert.has_list:
        raise InputError("PLY vertex element has list properties; not a Gaussian splat file", path)
    if fmt == "ascii":
        text = raw[body:].decode("ascii", errors="replace").split("\n")
        skip = sum(e.count for e in elements[:vi])
        rows = [r for r in text[skip:skip + vert.count]]
        if len(rows) < vert.count:
            raise InputError(f"PLY is truncated: header says {vert.count} vertices, file has {len(rows)}", path)
        try:
            arr = np.array([r.split() for r in rows], dtype=np.float64)
        except ValueError:
            raise InputError("PLY ascii vertex rows have inconsistent or non-numeric values", path) from None
        if vert.count and arr.shape != (vert.count, len(vert.props)):
            raise InputError(f"PLY ascii vertex rows must have {len(vert.props)} values each", path)
        arr = arr.reshape(vert.count, len(vert.props))
        return {n: arr[:, i] for i, (n, _) in enumerate(vert.props)}
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = body
    for e in elements[:vi]:
        if e.has_list:
            raise InputError(f"PLY element {e.name!r} before 'vertex' has list properties (unsupported)", path)
        offset += e.count * int(sum(np.dtype(t).itemsize for _, t in e.props))
    dtype = np.dtype([(n, endian + t) for n, t in vert.props])
    need = vert.count * dtype.itemsize
    have = len(raw) - offset
    if have < need:
        raise InputError(f"PLY is truncated: header says {vert.count} vertices ({need} bytes), "
                         f"file has {max(have, 0)} bytes of vertex data", path)
    rec = np.frombuffer(raw, dtype=dtype, count=vert.count, offset=offset)
    return {n: rec[n].astype(np.float64) for n, _ in vert.props}


def read_gaussians_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS PLY into activated `Gaussians` (see module docstring for accepted variants)."""
    path = Path(path)
    v = read_ply_vertices(path)
    if "packed_position" in v or "min_x" in v:
        raise InputError("compressed (SuperSplat packed) PLY is not supported; decompress it first", path)
    missing = [n for n in _REQUIRED if n not in v]
    has_dc = all(f"f_dc_{i}" in v for i in range(3))
    has_rgb = all(c in v for c in ("red", "green", "blue"))
    if not has_dc and not has_rgb:
        missing += ["f_dc_0", "f_dc_1", "f_dc_2"]
    if missing:
        raise InputError(f"not a 3DGS PLY: vertex properties missing: {', '.join(missing)}", path)
    n = len(v["x"])
    n_rest = 0
    while f"f_rest_{n_rest}" in v:
        n_rest += 1
    if n_rest % 3 != 0:
        raise InputError(f"{n_rest} f_rest properties is not a multiple of 3", path)
    try:
        degree = sh_degree_from_bases(n_rest // 3 + 1)
    except ValueError:
        raise InputError(f"{n_rest} f_rest properties does not match any SH degree "
                         f"(expected 0, 9, 24 or 45)", path) from None
    if n == 0:  # a valid, empty splat: callers that need Gaussians say so with their own message
        return Gaussians.empty(degree)
    k = (degree + 1) ** 2
    sh = np.zeros((n, k, 3))
    if has_dc:
        sh[:, 0, :] = np.stack([v[f"f_dc_{i}"] for i in range(3)], axis=1)
    else:  # plain coloured point cloud: uchar colours -> DC
        rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
        sh[:, 0, :] = rgb_to_sh0(rgb / 255.0 if rgb.max(initial=0) > 1.0 else rgb)
    if n_rest:
        rest = np.stack([v[f"f_rest_{i}"] for i in range(n_rest)], axis=1)
        sh[:, 1:, :] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    means = np.stack([v["x"], v["y"], v["z"]], axis=1)
    log_scales = np.stack([v[f"scale_{i}"] for i in range(3)], axis=1)
    quats = np.stack([v[f"rot_{i}"] for i in range(4)], axis=1)
    logits = v["opacity"]
    for name, a in (("positions", means), ("SH colours", sh), ("opacity", logits), ("scales", log_scales),
                    ("rotations", quats)):
        bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
        if bad.any():
            raise InputError(f"{int(bad.sum())} Gaussians have NaN or infinite {name} "
                             f"(first at vertex {int(np.argmax(bad))})", path)
    qn = np.linalg.norm(quats, axis=1)
    if np.any(qn == 0):
        raise InputError(f"{int(np.sum(qn == 0))} Gaussians have a zero quaternion", path)
    # Normalise, but keep quaternions already unit to float32 precision exactly as stored, so that
    # load -> save reproduces our own files bit for bit.
    off = np.abs(qn - 1.0) > 1e-6
    quats[off] /= qn[off, None]
    with np.errstate(over="ignore"):  # a finite log-scale above ~709 has no finite scale: refused below
        scales = np.exp(log_scales)
        opacities = 1.0 / (1.0 + np.exp(-logits))  # a logit below ~-709: exp -> inf, opacity 0 (as before)
    bad = ~np.isfinite(scales).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{int(bad.sum())} Gaussians have a log-scale too large for a finite scale (first at "
                         f"vertex {i}: log-scales {', '.join(f'{x:.6g}' for x in log_scales[i])})", path)
    try:
        return Gaussians(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh)
    except InputError as e:  # the values checks of `Gaussians.validate`: name the file
        if e.path is not None:
            raise
        raise InputError(e.problem, path) from None
