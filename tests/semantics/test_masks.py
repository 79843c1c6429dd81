"""RLE codec against known pycocotools encodings; MaskSet round trips through every layout; bad input."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from splattwin import io
from splattwin.errors import InputError
from splattwin.semantics import rle
from splattwin.semantics.masks import (MaskSet, load_coco, load_masks, polygons_to_mask, save_coco,
                                       save_polygon_dir)


def _square(lo, hi, n=25):
    m = np.zeros((n, n), bool)
    m[lo:hi, lo:hi] = True
    return m


# Encodings produced by pycocotools.mask.encode (published in pycocotools-compatible test suites).
KNOWN = [(_square(0, 5), "05d00000000d?"), (_square(5, 10), "R45d00000000b;"), (_square(20, 25), "X`05d00000000")]


@pytest.mark.parametrize("mask,expected", KNOWN)
def test_rle_matches_pycocotools(mask, expected):
    enc = rle.encode(mask)
    assert enc == {"size": [25, 25], "counts": expected}
    assert np.array_equal(rle.decode({"size": [25, 25], "counts": expected}), mask)


def test_rle_known_small_and_uncompressed():
    assert rle.string_to_counts("52203") == [5, 2, 2, 2, 5]
    assert rle.counts_to_string([5, 2, 2, 2, 5]) == "52203"
    m = rle.decode({"size": [4, 4], "counts": [5, 2, 2, 2, 5]})
    assert m.sum() == 4 and m[1, 1] and m[2, 1] and m[1, 2] and m[2, 2]  # column-major runs
    assert rle.mask_to_counts(np.ones((2, 2), bool)) == [0, 4]           # leading empty zero run


def test_rle_round_trip_random():
    rng = np.random.default_rng(1)
    for shape in [(1, 1), (7, 3), (40, 57), (128, 96)]:
        for p in (0.0, 0.05, 0.5, 1.0):
            m = rng.random(shape) < p
            assert np.array_equal(rle.decode(rle.encode(m)), m)
            assert np.array_equal(rle.decode(rle.encode(m, compressed=False)), m)
    big = np.zeros((600, 800), bool)
    big[100:500, 50:700] = True  # long runs -> multi-group and negative deltas
    assert np.array_equal(rle.decode(rle.encode(big)), big)


def test_rle_bad_counts():
    with pytest.raises(InputError, match="pixels"):
        rle.decode({"size": [4, 4], "counts": [5, 2]})
    with pytest.raises(InputError):
        rle.decode({"counts": "52203"})


def _maskset():
    ms = MaskSet(objects={1: "blue_box", 3: "toy hammer"}, prompts={1: "blue box"})
    a = np.zeros((20, 30), bool)
    a[2:9, 4:15] = True
    b = np.zeros((20, 30), bool)
    b[10:18, 20:28] = True
    ms.add("v0", 1, a, 0.9)
    ms.add("v0", 3, b, 0.5)
    ms.add("v1", 1, b, 1.0)
    ms.sizes["v2"] = (20, 30)  # a view where nothing was found
    return ms


def _same(x: MaskSet, y: MaskSet, scores=True):
    assert x.objects == y.objects
    assert set(x.masks) == set(y.masks)
    for v in x.masks:
        assert set(x.masks[v]) == set(y.masks[v])
        for k in x.masks[v]:
            assert np.array_equal(x.get(v, k), y.get(v, k)), (v, k)
            if scores:
                assert x.scores[v][k] == pytest.approx(y.scores[v][k])


def test_maskset_save_load(tmp_path):
    ms = _maskset()
    ms.save(tmp_path / "m")
    back = MaskSet.load(tmp_path / "m")
    _same(ms, back)
    assert back.sizes["v2"] == (20, 30) and back.prompts == {1: "blue box"}


def test_coco_round_trip(tmp_path):
    ms = _maskset()
    save_coco(ms, tmp_path / "ann.json")
    back = load_masks(tmp_path / "ann.json", objects={"blue_box": 1, "toy hammer": 3})
    _same(ms, back)
    # list-counts RLE and polygons are read too
    d = json.loads((tmp_path / "ann.json").read_text())
    d["annotations"][0]["segmentation"] = rle.encode(ms.get("v0", 1), compressed=False)
    d["annotations"][1]["segmentation"] = [[20, 10, 27, 10, 27, 17, 20, 17]]
    io.write_json(tmp_path / "ann2.json", d)
    back2 = load_coco(tmp_path / "ann2.json", {"blue_box": 1, "toy hammer": 3})
    assert np.array_equal(back2.get("v0", 1), ms.get("v0", 1))
    assert np.array_equal(back2.get("v0", 3), ms.get("v0", 3))  # filled polygon incl. its border pixels


def test_polygon_layout_round_trip(tmp_path):
    ms = _maskset()
    save_polygon_dir(ms, tmp_path / "poly")
    f = tmp_path / "poly" / "blue_box" / "v0_mask.json"
    d = json.loads(f.read_text())
    assert {"image_filename", "image_height", "image_width", "segmentation_polygons"} <= set(d)
    assert isinstance(d["segmentation_polygons"][0][0], list) and len(d["segmentation_polygons"][0][0]) == 2
    back = load_masks(tmp_path / "poly", objects={"blue_box": 1, "toy_hammer": 3})
    assert np.array_equal(back.get("v0", 1), ms.get("v0", 1))
    assert np.array_equal(back.get("v1", 1), ms.get("v1", 1))
    # the published code's flat layout: one object per folder, name from the folder
    flat = tmp_path / "hammer"
    io.write_json(flat / "img7_mask.json", {"image_filename": "img7.png", "image_height": 10, "image_width": 12,
                                            "input_points": [[5, 5]], "input_labels": [1],
                                            "segmentation_polygons": [[[2, 2], [6, 2], [6, 5], [2, 5]]]})
    one = load_masks(flat)
    assert one.objects == {1: "hammer"} and one.get("img7", 1).sum() == 5 * 4
    assert polygons_to_mask([], 4, 4).sum() == 0


def test_png_and_label_images(tmp_path):
    a = np.zeros((8, 10), np.uint8)
    a[1:4, 2:6] = 255
    io.write_image(tmp_path / "png" / "train_000" / "cube.png", a)
    io.write_image(tmp_path / "png" / "train_001" / "cube.png", np.zeros_like(a))
    ms = load_masks(tmp_path / "png", objects={"cube": 4})
    assert ms.objects == {4: "cube"} and ms.get("train_000", 4).sum() == 12 and ms.n_views_with(4) == 1
    lab = np.zeros((8, 10), np.uint8)
    lab[2:5, 1:3] = 2
    lab[6:8, 6:10] = 5
    io.write_image(tmp_path / "gt" / "train_000.png", lab)
    g = load_masks(tmp_path / "gt", objects={"a": 2, "b": 5})
    assert g.get("train_000", 2).sum() == 6 and g.get("train_000", 5).sum() == 8


def test_bad_inputs(tmp_path):
    ms = _maskset()
    with pytest.raises(InputError, match="are 30x20 but its image is 40x20") as e:
        ms.validate({"v0": (20, 40), "v1": (20, 30), "v2": (20, 30)})
    assert "turned" not in e.value.problem
    # masks drawn on a phone photo's stored (sideways) pixels: the size turned by 90 degrees, said so
    with pytest.raises(InputError, match="are 30x20 but its image is 20x30 .turned by 90 degrees.*EXIF Orientation"):
        ms.validate({"v0": (30, 20), "v1": (20, 30), "v2": (20, 30)})
    with pytest.raises(InputError, match="empty mask set"):
        MaskSet().validate()
    ms.objects[7] = "ghost"
    with pytest.raises(InputError, match="'ghost'.*seen in no view"):
        ms.validate()
    with pytest.raises(InputError, match="other masks of that view"):
        _maskset().add("v0", 1, np.zeros((5, 5), bool))
    with pytest.raises(InputError, match="does not exist"):
        load_masks(tmp_path / "nope")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_masks(tmp_path / "bad.json")
    io.write_json(tmp_path / "c.json", {"images": [{"id": 1, "file_name": "a.png", "height": 4, "width": 4}],
                                       "categories": [{"id": 1, "name": "x"}],
                                       "annotations": [{"image_id": 1, "category_id": 1,
                                                        "segmentation": {"size": [5, 4], "counts": [20]}}]})
    with pytest.raises(InputError, match="differs from its image"):
        load_masks(tmp_path / "c.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _maskset().validate()  # a valid set raises nothing


# -- untrusted files: numbers, names and sizes ---------------------------------------------------------------
def _coco(**change) -> dict:
    """A one-image, one-category COCO dict; `change` replaces parts: image=, category=, annotation=, extra=."""
    im = {"id": 1, "file_name": "v0.png", "height": 4, "width": 4, **change.get("image", {})}
    cat = {"id": 1, "name": "mug", **change.get("category", {})}
    ann = {"image_id": 1, "category_id": 1, "segmentation": {"size": [4, 4], "counts": [5, 2, 2, 2, 5]},
           **change.get("annotation", {})}
    return {"images": [im] + change.get("extra", []), "categories": [cat], "annotations": [ann]}


@pytest.mark.parametrize("change,message", [
    ({"category": {"id": float("inf")}}, "category id must be a whole number, got inf"),
    ({"category": {"id": 1.7}}, "category id must be a whole number, got 1.7"),
    ({"image": {"height": float("inf")}}, "size must be whole numbers"),
    ({"annotation": {"segmentation": {"size": [float("inf"), 4], "counts": [16]}}}, "annotation 0 RLE size"),
    ({"image": {"id": 1.7}}, "image id must be a whole number, got 1.7"),
    ({"annotation": {"image_id": 1.7}}, "annotation 0 image_id must be a whole number"),
    ({"extra": [{"id": 1, "file_name": "v1.png", "height": 4, "width": 4}]}, "image id 1 appears twice"),
    ({"extra": [{"id": 2, "file_name": "v0.jpg", "height": 4, "width": 4}]}, "two images have the view name 'v0'"),
    ({"image": {"file_name": ["v0.png"]}}, r"file_name must be a string, got \['v0.png'\]"),
    ({"annotation": {"score": float("nan")}}, "score must be a number in .0, 1., got nan"),
    ({"annotation": {"score": float("inf")}}, "score must be a number in .0, 1., got inf"),
    ({"annotation": {"score": 1e6}}, "score must be a number in .0, 1."),
    ({"annotation": {"score": "x"}}, "score must be a number in .0, 1."),
])
def test_coco_bad_numbers_names_and_duplicates(tmp_path, change, message):
    f = tmp_path / "c.json"
    f.write_text(json.dumps(_coco(**change)).replace("Infinity", "1e400"))   # as a file would spell it
    with pytest.raises(InputError, match=message) as e:
        load_masks(f)
    assert e.value.path == f
    io.write_json(f, _coco())
    assert load_masks(f).get("v0", 1).sum() == 4   # the unchanged file loads


def test_coco_integer_too_long_for_python(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps(_coco()).replace('"id": 1,', '"id": 1' + "0" * 5000 + ",", 1))
    with pytest.raises(InputError, match="number too long") as e:
        load_masks(f)
    assert e.value.path == f


def test_coco_categories_bounded(tmp_path):
    from splattwin.semantics.masks import MAX_CATEGORIES

    d = _coco()
    d["categories"] = [{"id": i, "name": f"c{i}"} for i in range(1, MAX_CATEGORIES + 2)]
    io.write_json(tmp_path / "c.json", d)
    with pytest.raises(InputError, match=f"at most {MAX_CATEGORIES}"):
        load_masks(tmp_path / "c.json")


def test_polygon_json_bad_size_and_score(tmp_path):
    d = {"image_filename": "v0.png", "image_height": 10, "image_width": 12, "input_points": [],
         "input_labels": [], "segmentation_polygons": [[[2, 2], [6, 2], [6, 5], [2, 5]]]}
    f = tmp_path / "hammer" / "v0_mask.json"
    for change, message in (({"image_height": float("inf")}, "size must be whole numbers"),
                            ({"score": "x"}, "score must be a number in .0, 1., got 'x'"),
                            ({"score": float("nan")}, "score must be a number"),
                            ({"image_filename": ["v0.png"]}, "image_filename must be a string")):
        f.parent.mkdir(exist_ok=True)
        f.write_text(json.dumps({**d, **change}).replace("Infinity", "1e400"))
        with pytest.raises(InputError, match=message) as e:
            load_masks(tmp_path / "hammer")
        assert e.value.path == f


def test_mask_index_bad_label_size_and_score(tmp_path):
    ms = _maskset()
    ms.save(tmp_path / "m")
    index = tmp_path / "m" / "masks.json"
    good = json.loads(index.read_text())
    for edit, message in ((lambda d: d["objects"][0].update(label=float("inf")), "label of object 'blue_box' must be"),
                          (lambda d: d["objects"][0].update(label=70000), r"outside \[1, 65535\]"),
                          (lambda d: d["views"]["v0"].update(size=[20, float("inf")]), "size must be whole numbers"),
                          (lambda d: d["views"]["v0"]["masks"]["blue_box"].update(score="x"), "score of 'blue_box'")):
        d = json.loads(json.dumps(good))
        edit(d)
        index.write_text(json.dumps(d).replace("Infinity", "1e400"))
        with pytest.raises(InputError, match=message) as e:
            MaskSet.load(tmp_path / "m")
        assert e.value.path == index


def test_mask_index_wrong_size_blames_the_index(tmp_path):
    ms = _maskset()
    ms.save(tmp_path / "m")
    index = tmp_path / "m" / "masks.json"
    d = json.loads(index.read_text())
    d["views"]["v0"]["size"] = [10, 10]
    index.write_text(json.dumps(d))
    with pytest.raises(InputError, match="masks.json says view 'v0' is 10x10 but its mask file v0/blue_box.png "
                                         "is 30x20") as e:
        MaskSet.load(tmp_path / "m")
    assert e.value.path == index
    with pytest.raises(InputError, match="mask of view 'v0' is 10x10 but its image is 30x20") as e:
        load_masks(tmp_path / "m", image_sizes={"v0": (20, 30)})
    assert e.value.path == index


def test_label_image_with_too_many_labels_is_refused_before_masks(tmp_path):
    from splattwin.semantics.masks import MAX_OBJECTS_PER_VIEW

    lab = np.arange(64 * 32, dtype=np.uint16).reshape(32, 64)   # 2047 labels in 2 KiB of pixels
    io.write_image(tmp_path / "gt" / "v0.png", lab)
    with pytest.raises(InputError, match=f"2047 distinct labels, more than the limit of {MAX_OBJECTS_PER_VIEW}") as e:
        load_masks(tmp_path / "gt")
    assert e.value.path == tmp_path / "gt" / "v0.png"
    few = np.zeros((32, 64), np.uint16)
    few[:4, :4], few[10:, 10:] = 7, 300
    io.write_image(tmp_path / "gt" / "v0.png", few)
    assert sorted(load_masks(tmp_path / "gt").objects) == [7, 300]


APPLEDOUBLE = b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        "


def test_hidden_appledouble_files_beside_masks_are_left_out(tmp_path):
    # a mask folder copied from a Mac to an exFAT drive has `._x.png` beside every file (and `._view` beside every
    # folder): none is a mask, and the first stopped the masks as an unreadable image
    a = np.zeros((8, 10), np.uint8)
    a[1:4, 2:6] = 255
    io.write_image(tmp_path / "png" / "train_000" / "cube.png", a)
    (tmp_path / "png" / "train_000" / "._cube.png").write_bytes(APPLEDOUBLE)
    (tmp_path / "png" / "._train_000").write_bytes(APPLEDOUBLE)
    ms = load_masks(tmp_path / "png", objects={"cube": 4})
    assert ms.objects == {4: "cube"} and ms.views == ["train_000"] and ms.get("train_000", 4).sum() == 12
    lab = np.zeros((8, 10), np.uint8)
    lab[2:5, 1:3] = 2
    io.write_image(tmp_path / "gt" / "train_000.png", lab)
    (tmp_path / "gt" / "._train_000.png").write_bytes(APPLEDOUBLE)
    g = load_masks(tmp_path / "gt", objects={"a": 2})
    assert g.views == ["train_000"] and g.get("train_000", 2).sum() == 6
    save_polygon_dir(_maskset(), tmp_path / "poly")
    (tmp_path / "poly" / "blue_box" / "._v0_mask.json").write_bytes(APPLEDOUBLE)
    back = load_masks(tmp_path / "poly", objects={"blue_box": 1, "toy_hammer": 3})
    assert np.array_equal(back.get("v0", 1), _maskset().get("v0", 1))
