"""The GLB export against the glTF 2.0 spec, as the Khronos validator and viewers (three.js, Blender) read it.

The GLB is parsed here by hand (JSON chunk + BIN chunk -> accessors), not through trimesh, so the checks see
exactly what a viewer sees (audit 10d G1-G3)."""

from __future__ import annotations

import json
import struct
import warnings

import numpy as np
import pytest
import trimesh

from splattwin.poses.twin_frame import TwinFrame
from splattwin.scene.synthetic import synthetic_scene
from splattwin.twin.build import build_twin
from splattwin.twin.gltf import TABLE_RGBA, linear_from_srgb

_DTYPES = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    g, labels, objects, _ = synthetic_scene(16000, seed=1, obstacle=True)
    out = tmp_path_factory.mktemp("twin_gltf")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = build_twin(g, labels, objects, out, TwinFrame("ground_truth", scaled=True), formats=("gltf",),
                       progress=False)
    return out, m


def read_glb(path):
    """(json tree, accessor(i) -> numpy array) of a GLB file."""
    data = path.read_bytes()
    n = struct.unpack("<I", data[12:16])[0]
    tree = json.loads(data[20:20 + n])
    bin_len = struct.unpack("<I", data[20 + n:24 + n])[0]
    blob = data[28 + n:28 + n + bin_len]

    def accessor(i):
        a = tree["accessors"][i]
        v = tree["bufferViews"][a["bufferView"]]
        start = v.get("byteOffset", 0) + a.get("byteOffset", 0)
        w = _WIDTH[a["type"]]
        arr = np.frombuffer(blob, dtype=_DTYPES[a["componentType"]], count=a["count"] * w, offset=start)
        return arr.reshape(a["count"], w)

    return tree, accessor


def _prim(tree, node_name):
    node = next(nd for nd in tree["nodes"] if nd.get("name") == node_name)
    return tree["meshes"][node["mesh"]]["primitives"][0]


def test_linear_from_srgb_values():
    # sRGB transfer function (IEC 61966-2-1): 0 and 1 fixed, mid-grey 188/255 ~ linear 0.5, 128 ~ 0.216
    out = linear_from_srgb([[0, 128, 188, 77], [255, 10, 255, 255]])
    assert out.dtype == np.uint8
    assert out[0].tolist() == [0, 55, 128, 77] and out[1].tolist() == [255, 1, 255, 255]   # alpha kept


def test_vertex_colours_are_linear(twin):
    """glTF COLOR_0 is linear (spec 3.7.2.1); the splats' colours and the table colour are sRGB: written raw
    they show washed out in every viewer."""
    out, m = twin
    tree, acc = read_glb(out / "export" / "scene.glb")
    table = acc(_prim(tree, "table")["attributes"]["COLOR_0"])
    assert np.all(table == linear_from_srgb(TABLE_RGBA, np.float32))
    assert not np.allclose(table, np.asarray(TABLE_RGBA) / 255.0)
    box = _prim(tree, "box")["attributes"]
    srgb = trimesh.load(out / m.object("box").visual_mesh, force="mesh", process=True).visual.vertex_colors
    written = acc(box["COLOR_0"])
    assert written.shape == srgb.shape
    # same vertex order as the processed OBJ (trimesh keeps it): the written colours are the linear ones
    assert np.array_equal(written, linear_from_srgb(srgb, np.float32))


def test_vertex_colours_are_float_so_dark_colours_stay_distinct(twin):
    """COLOR_0 is float (allowed by glTF 3.7.2.1): in linear 8-bit the sRGB levels 0..13 all fell on linear 0
    or 1/255 (a dark object posterised); as floats each keeps its own level. No custom attribute is left in
    the file, and trimesh reads the colours back as the sRGB-to-linear bytes (it misreads 16-bit ones)."""
    out, _ = twin
    tree, acc = read_glb(out / "export" / "scene.glb")
    for name in ("table", "box"):
        prim = _prim(tree, name)["attributes"]
        a = tree["accessors"][prim["COLOR_0"]]
        assert a["componentType"] == 5126 and "normalized" not in a and a["type"] == "VEC4"
        assert 0.0 <= acc(prim["COLOR_0"]).min() and acc(prim["COLOR_0"]).max() <= 1.0
        assert not [k for k in prim if k.startswith("_")]
    dark = linear_from_srgb(np.stack([np.arange(14)] * 3 + [np.full(14, 255)], axis=1), np.float32)
    assert len(np.unique(dark[:, 0])) == 14
    back = trimesh.load(out / "export" / "scene.glb").geometry["table"].visual.vertex_colors
    assert np.array_equal(back[0], linear_from_srgb(TABLE_RGBA))
    assert len(np.unique(linear_from_srgb(np.stack([np.arange(14)] * 4, axis=1))[:, 0])) == 2   # 8-bit: 2 levels


def test_every_primitive_has_unit_normals(twin):
    """Without NORMAL viewers must shade flat (spec 3.7.2.1); the validator wants them unit length. Boxes get
    face normals (axis-aligned), not corner-averaged ones that would shade the table as rounded."""
    out, _ = twin
    tree, acc = read_glb(out / "export" / "scene.glb")
    for mesh in tree["meshes"]:
        for prim in mesh["primitives"]:
            nrm = acc(prim["attributes"]["NORMAL"]).astype(float)
            assert len(nrm) == len(acc(prim["attributes"]["POSITION"]))
            assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5), mesh.get("name")
    table = acc(_prim(tree, "table")["attributes"]["NORMAL"]).astype(float)
    assert np.allclose(np.abs(table).max(axis=1), 1.0, atol=1e-6)   # each one is +-x, +-y or +-z


def test_buffer_views_say_vertex_or_index(twin):
    """Khronos validator BUFFER_VIEW_TARGET_MISSING: bufferView.target for vertex (34962) and index (34963) data."""
    out, _ = twin
    tree, _ = read_glb(out / "export" / "scene.glb")
    views, acc = tree["bufferViews"], tree["accessors"]
    for mesh in tree["meshes"]:
        for prim in mesh["primitives"]:
            for a in prim["attributes"].values():
                assert views[acc[a]["bufferView"]].get("target") == 34962
            assert views[acc[prim["indices"]]["bufferView"]].get("target") == 34963
