from __future__ import annotations

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.splat.gaussians import Gaussians
from splattwin.splat.ply import property_names, read_ply_vertices


def random_gaussians(n: int = 50, degree: int = 3, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(means=rng.normal(size=(n, 3)), quats=q, scales=np.exp(rng.uniform(-6, -1, size=(n, 3))),
                     opacities=rng.uniform(0.01, 0.99, size=n), sh=rng.normal(size=(n, (degree + 1) ** 2, 3)))


def write_ply(path, names, rows, fmt="binary_little_endian", types=None, extra_elements=""):
    types = types or ["float"] * len(names)
    header = ["ply", f"format {fmt} 1.0", "comment test"]
    if extra_elements:
        header.append(extra_elements)
    header.append(f"element vertex {len(rows)}")
    header += [f"property {t} {n}" for t, n in zip(types, names)]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode()
    rows = np.asarray(rows, dtype=np.float64)
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(x)) for x in r) + "\n" for r in rows).encode()
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        code = {"float": "f4", "double": "f8", "uchar": "u1"}
        dt = np.dtype([(n, end + code[t]) for n, t in zip(names, types)])
        rec = np.zeros(len(rows), dtype=dt)
        for i, n in enumerate(names):
            rec[n] = rows[:, i]
        body = rec.tobytes()
    path.write_bytes(head + body)
    return path


def standard_rows(g: Gaussians) -> np.ndarray:
    from splattwin.splat.ply import gaussians_to_array
    return gaussians_to_array(g).astype(np.float64)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_bit_exact(tmp_path, degree):
    g = random_gaussians(degree=degree)
    a = g.save_ply(tmp_path / "a.ply")
    g2 = Gaussians.load_ply(a)
    b = g2.save_ply(tmp_path / "b.ply")
    assert a.read_bytes() == b.read_bytes()
    assert g2.sh_degree == degree and len(g2) == len(g)
    np.testing.assert_allclose(g2.means, g.means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(g2.scales, g.scales, rtol=1e-5)
    np.testing.assert_allclose(g2.opacities, g.opacities, rtol=1e-5)
    np.testing.assert_allclose(g2.sh, g.sh, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g2.quats, axis=1), 1.0, atol=1e-6)


def test_standard_layout_channel_major(tmp_path):
    g = random_gaussians(n=3, degree=1)
    p = g.save_ply(tmp_path / "g.ply")
    head = p.read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in head
    names = [ln.split()[-1] for ln in head.splitlines() if ln.startswith("property")]
    assert names == property_names(1)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    v = read_ply_vertices(p)
    # f_rest_0..2 are the three degree-1 coefficients of the red channel (channel-major).
    np.testing.assert_allclose(v["f_rest_0"], g.sh[:, 1, 0], rtol=1e-6)
    np.testing.assert_allclose(v["f_rest_2"], g.sh[:, 3, 0], rtol=1e-6)
    np.testing.assert_allclose(v["f_rest_3"], g.sh[:, 1, 1], rtol=1e-6)
    np.testing.assert_allclose(v["opacity"], np.log(g.opacities / (1 - g.opacities)), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(v["scale_0"], np.log(g.scales[:, 0]), rtol=1e-6)


def test_foreign_ascii_double_extra_props_degree0(tmp_path):
    g = random_gaussians(n=7, degree=0)
    rows = standard_rows(g)
    names = property_names(0)
    # Another tool: ascii, double precision, extra per-vertex fields, properties shuffled.
    order = list(reversed(range(len(names))))
    names2 = [names[i] for i in order] + ["confidence", "label"]
    rows2 = np.concatenate([rows[:, order], np.ones((len(g), 2))], axis=1)
    p = write_ply(tmp_path / "f.ply", names2, rows2, fmt="ascii", types=["double"] * len(names2))
    g2 = Gaussians.load_ply(p)
    assert g2.sh_degree == 0 and len(g2) == 7
    np.testing.assert_allclose(g2.means, g.means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(g2.opacities, g.opacities, rtol=1e-5)


def test_foreign_big_endian_with_preceding_element_and_no_normals(tmp_path):
    g = random_gaussians(n=5, degree=2)
    rows = standard_rows(g)
    keep = [i for i, n in enumerate(property_names(2)) if n not in ("nx", "ny", "nz")]
    names = [property_names(2)[i] for i in keep]
    p = tmp_path / "be.ply"
    write_ply(p, names, rows[:, keep], fmt="binary_big_endian")
    g2 = Gaussians.load_ply(p)
    assert g2.sh_degree == 2
    np.testing.assert_allclose(g2.sh, g.sh, rtol=1e-6, atol=1e-6)


def test_malformed_files(tmp_path):
    g = random_gaussians(n=4, degree=0)
    rows = standard_rows(g)
    names = property_names(0)
    (tmp_path / "x.ply").write_bytes(b"hello world")
    with pytest.raises(InputError, match="not a PLY"):
        Gaussians.load_ply(tmp_path / "x.ply")
    with pytest.raises(InputError, match="not found"):
        Gaussians.load_ply(tmp_path / "missing.ply")
    drop = [i for i, n in enumerate(names) if n != "scale_1"]
    p = write_ply(tmp_path / "m.ply", [names[i] for i in drop], rows[:, drop])
    with pytest.raises(InputError, match="scale_1") as e:
        Gaussians.load_ply(p)
    assert e.value.path == p
    bad = rows.copy()
    bad[2, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        Gaussians.load_ply(write_ply(tmp_path / "n.ply", names, bad))
    bad = rows.copy()
    bad[1, names.index("opacity")] = np.inf
    with pytest.raises(InputError, match="opacity"):
        Gaussians.load_ply(write_ply(tmp_path / "i.ply", names, bad))
    full = write_ply(tmp_path / "t.ply", names, rows).read_bytes()
    (tmp_path / "t.ply").write_bytes(full[:-10])
    with pytest.raises(InputError, match="truncated"):
        Gaussians.load_ply(tmp_path / "t.ply")
    # vertex count in the header larger than the rows of an ascii file
    p = write_ply(tmp_path / "c.ply", names, rows, fmt="ascii")
    p.write_bytes(p.read_bytes().replace(b"element vertex 4", b"element vertex 9"))
    with pytest.raises(InputError, match="truncated"):
        Gaussians.load_ply(p)
    # 4 f_rest coefficients matches no SH degree
    names_r = names[:9] + [f"f_rest_{i}" for i in range(4)] + names[9:]
    rows_r = np.concatenate([rows[:, :9], np.zeros((4, 4)), rows[:, 9:]], axis=1)
    with pytest.raises(InputError, match="f_rest"):
        Gaussians.load_ply(write_ply(tmp_path / "r.ply", names_r, rows_r))
    # zero quaternion
    bad = rows.copy()
    bad[:, names.index("rot_0"):] = 0
    with pytest.raises(InputError, match="quaternion"):
        Gaussians.load_ply(write_ply(tmp_path / "q.ply", names, bad))


def test_plain_point_cloud_colours(tmp_path):
    # Some tools write uchar red/green/blue instead of f_dc_*.
    names = ["x", "y", "z", "red", "green", "blue", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    types = ["float"] * 3 + ["uchar"] * 3 + ["float"] * 8
    rows = [[0, 0, 0, 255, 0, 51, 0.0, -3, -3, -3, 1, 0, 0, 0]]
    g = Gaussians.load_ply(write_ply(tmp_path / "c.ply", names, rows, types=types))
    np.testing.assert_allclose(g.colors[0], [1.0, 0.0, 0.2], atol=1e-9)
    np.testing.assert_allclose(g.opacities, [0.5])
