import json
import logging

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import cameras_json, colmap, images, nerfstudio
from splattwin.capture.dataset import Dataset, load_dataset, load_depth, load_image
from splattwin.errors import InputError



def assert_same_cameras(a: Dataset, b: Dataset, check_split: bool = True, atol: float = 1e-9):
    assert len(a.frames) == len(b.frames)
    by_name = {f.image_path.name: f for f in b.frames}
    for fa in a.frames:
        fb = by_name[fa.image_path.name]
        np.testing.assert_allclose(fb.camera.K, fa.camera.K, atol=atol)
        np.testing.assert_allclose(fb.camera.T_world_cam, fa.camera.T_world_cam, atol=atol)
        assert (fb.camera.width, fb.camera.height) == (fa.camera.width, fa.camera.height)
        if fa.camera.dist is None:
            assert fb.camera.dist is None
        else:
            np.testing.assert_allclose(fb.camera.dist[:4], fa.camera.dist[:4], atol=atol)
        if check_split:
            assert fb.split == fa.split


def test_nerfstudio_roundtrip(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, dist=np.array([0.01, -0.002, 0.0005, 0.0001]), with_depth=True)
    labels = tmp_path / "labels" / "img_000.png"
    io.write_image(labels, np.zeros((48, 64), np.uint8))
    ds.frames[0].label_path = labels
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    back = load_dataset(out)
    assert_same_cameras(ds, back)
    assert back.frames[0].label_path == labels and back.frames[0].mask_path is None
    assert back.frames[1].label_path is None
    assert [f.depth_path.name for f in back.frames] == [f.depth_path.name for f in ds.frames]
    np.testing.assert_allclose(back.points_xyz, ds.points_xyz, atol=1e-6)
    np.testing.assert_array_equal(back.points_rgb, ds.points_rgb)
    meta = json.loads(out.read_text())
    assert meta["camera_model"] == "OPENCV" and "k1" in meta
    assert meta["test_filenames"] == ["images/img_003.png"]
    # the folder is detected too
    assert len(load_dataset(tmp_path).frames) == 4
    d = load_depth(back.frames[0].depth_path)
    assert d.dtype == np.float32 and d.shape == (48, 64)


def test_nerfstudio_per_frame_intrinsics(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, per_frame_K=True, with_points=False)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    meta = json.loads(out.read_text())
    assert "fl_x" not in meta and "fl_x" in meta["frames"][0]
    assert_same_cameras(ds, load_dataset(out))


def test_nerfstudio_split_lists_and_missing_image(tmp_path, caplog, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    meta = json.loads(out.read_text())
    # nerfstudio's parser wants a list for each split it loads once any is given (ns-train evaluates "val")
    assert meta["val_filenames"] == meta["test_filenames"] == ["images/img_003.png"]
    assert len(meta["train_filenames"]) == 3
    for fr in meta["frames"]:
        del fr["split"]  # only the nerfstudio split lists remain
    meta["frames"].append({"file_path": "images/gone.png", "transform_matrix": np.eye(4).tolist()})
    io.write_json(out, meta)
    with caplog.at_level(logging.WARNING):
        back = load_dataset(out)
    assert "gone.png" in caplog.text
    assert [f.split for f in back.frames] == ["train", "train", "train", "heldout"]
    # for work on cameras alone (the geometry stage's carving) the frame without its image is kept
    cams = load_dataset(out, require_images=False)
    assert [f.name for f in cams.frames] == [f.name for f in back.frames] + ["gone"]
    np.testing.assert_allclose(cams.frames[-1].camera.T_world_cam, np.diag([1.0, -1.0, -1.0, 1.0]))  # GL identity


@pytest.mark.parametrize("mutate, msg", [
    (lambda m: m.update(camera_model="EQUIRECTANGULAR"), "unsupported camera_model"),
    (lambda m: m["frames"][0].update(transform_matrix=[[float("nan")] * 4] * 4), "not finite"),
    (lambda m: m["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]), "4x4"),
    (lambda m: m.pop("fl_x"), "missing intrinsics"),
    (lambda m: m.pop("frames"), "no 'frames'"),
])
def test_nerfstudio_bad_input(tmp_path, mutate, msg, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    meta = json.loads(out.read_text())
    mutate(meta)
    io.write_json(out, meta)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(out)
    assert e.value.path == out


def test_invalid_json_names_file(tmp_path):
    p = tmp_path / "transforms.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON") as e:
        load_dataset(p)
    assert e.value.path == p


def test_image_size_mismatch_is_reported(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    io.write_image(ds.frames[1].image_path, np.zeros((10, 10, 3), np.uint8))
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    with pytest.raises(InputError, match="10x10") as e:
        load_dataset(out)
    assert e.value.path == ds.frames[1].image_path


def test_unreadable_image(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    ds.frames[0].image_path.write_bytes(b"not a png")
    with pytest.raises(InputError, match="unreadable image"):
        load_image(ds.frames[0].image_path)
    with pytest.raises(InputError, match="does not exist"):
        load_image(tmp_path / "nope.png")


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_roundtrip(tmp_path, binary, make_dataset):
    import pycolmap

    ds = make_dataset(tmp_path, dist=np.array([0.02, -0.01, 0.001, 0.002]))
    sparse = tmp_path / "sparse" / "0"
    colmap.write_text(ds, sparse)
    if binary:
        rec = pycolmap.Reconstruction(str(sparse))
        for f in sparse.glob("*.txt"):
            f.unlink()
        rec.write_binary(str(sparse))
        assert (sparse / "images.bin").is_file()
    back = load_dataset(tmp_path)
    assert back.meta["format"] == "colmap"
    assert_same_cameras(ds, back, check_split=False, atol=1e-7)
    np.testing.assert_allclose(np.sort(back.points_xyz, axis=0), np.sort(ds.points_xyz, axis=0), atol=1e-9)


def test_colmap_text_model_keeps_image_names_with_spaces(tmp_path, make_dataset, caplog):
    # COLMAP writes `f 4.jpg` into images.txt as it is, but reads (as pycolmap does) only `f`: every such image
    # became the missing `images/f`, skipped with a warning, and the capture went on with the others alone
    ds = make_dataset(tmp_path)
    for i, f in enumerate(ds.frames):
        spaced = f.image_path.with_name(f"cake photo {i}.png")
        f.image_path.rename(spaced)
        f.image_path = spaced
    with caplog.at_level(logging.WARNING, logger="splattwin.capture.colmap"):
        colmap.write_text(ds, tmp_path / "sparse" / "0")
    assert "4 image names hold spaces (cake photo 0.png, cake photo 1.png, cake photo 2.png, ...)" in caplog.text
    back = load_dataset(tmp_path)
    assert sorted(f.image_path.name for f in back.frames) == [f"cake photo {i}.png" for i in range(4)]
    assert sorted(f.camera.name for f in back.frames) == [f"cake photo {i}" for i in range(4)]
    assert_same_cameras(ds, back, check_split=False, atol=1e-7)


def test_colmap_unknown_model(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    sparse = tmp_path / "sparse" / "0"
    colmap.write_text(ds, sparse)
    lines = (sparse / "cameras.txt").read_text().splitlines()
    lines[1] = "1 FOV 64 48 50.0 50.5 32.5 23.75 0.1"  # a valid COLMAP model we cannot represent
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="unsupported COLMAP camera model FOV"):
        load_dataset(tmp_path)


def test_cameras_json_roundtrip(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    for f in ds.frames:  # cameras.json stores centred principal points only
        f.camera.K[0, 2], f.camera.K[1, 2] = 32.0, 24.0
    out = cameras_json.write(ds, tmp_path / "cameras.json")
    back = load_dataset(out)
    assert back.meta["format"] == "cameras.json"
    assert_same_cameras(ds, back, check_split=False)
    back.frames[0].image_path.unlink()  # an image gone: refused, unless only the cameras are wanted
    with pytest.raises(InputError, match="not found"):
        load_dataset(out)
    cams = {f.name: f.camera for f in load_dataset(out, require_images=False).frames}
    assert sorted(cams) == sorted(f.name for f in ds.frames)
    for f in ds.frames:
        np.testing.assert_allclose(cams[f.name].T_world_cam, f.camera.T_world_cam, atol=1e-9)


def test_cameras_json_rejects_offcentre(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    with pytest.raises(InputError, match="centred"):
        cameras_json.write(ds, tmp_path / "cameras.json")


def test_image_folder(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    back = load_dataset(tmp_path / "images")
    assert not back.has_poses and len(back.frames) == 4
    assert back.frames[0].camera.width == 64
    # photos of several sizes (internet photos, several cameras) are accepted: one camera per frame
    io.write_image(ds.frames[2].image_path, np.zeros((20, 30, 3), np.uint8))
    mixed = images.read(tmp_path / "images")
    sizes = [(f.camera.width, f.camera.height) for f in mixed.frames]
    assert sizes[2] == (30, 20) and sizes[0] == (64, sizes[0][1]) and len(set(sizes)) == 2
    assert mixed.frames[2].camera.cx == 15.0 and mixed.frames[2].camera.cy == 10.0
    mixed.validate()  # each image matches its own camera


def test_empty_folder(tmp_path):
    with pytest.raises(InputError, match="no dataset found"):
        load_dataset(tmp_path)


def test_max_frames_subsamples(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, n=6, with_points=False)
    nerfstudio.write(ds, tmp_path / "transforms.json")
    assert len(load_dataset(tmp_path, max_frames=3).frames) == 3


def _binary_model(tmp_path, make_dataset):
    import pycolmap

    ds = make_dataset(tmp_path)
    sparse = tmp_path / "sparse" / "0"
    colmap.write_text(ds, sparse)
    rec = pycolmap.Reconstruction(str(sparse))
    for f in sparse.glob("*.txt"):
        f.unlink()
    rec.write_binary(str(sparse))
    return sparse


@pytest.mark.parametrize("file,offset,what", [
    ("images.bin", None, "number of 2D points of image"),    # the first image's count (after its name)
    ("points3D.bin", 0, "number of 3D points"),
    ("points3D.bin", 8 + 43, "track length of 3D point 0"),
    ("cameras.bin", 0, "number of cameras"),
])
def test_colmap_binary_counts_are_bounded_by_the_file_before_pycolmap_allocates(tmp_path, make_dataset, file, offset,
                                                                                  what):
    """A uint64 count patched to 2^40 made pycolmap reserve 15-17 GB (then bad_alloc): each count is
    checked against the bytes the file holds before pycolmap reads it."""
    import struct

    sparse = _binary_model(tmp_path, make_dataset)
    raw = bytearray((sparse / file).read_bytes())
    if offset is None:   # uint64 num_images, then uint32 id, 7 doubles, uint32 camera id, the name, its count
        offset = raw.index(b"\0", 8 + 4 + 56 + 4) + 1
    struct.pack_into("<Q", raw, offset, 1 << 40)
    (sparse / file).write_bytes(bytes(raw))
    with pytest.raises(InputError, match=what) as e:
        load_dataset(tmp_path)
    assert e.value.path == sparse / file


@pytest.mark.parametrize("file, offset, fmt, what", [
    ("frames.bin", 0, "<Q", "number of frames"),
    ("frames.bin", 8 + 4 + 4 + 56, "<I", "number of images of frame 1"),   # after the first frame's pose
    ("rigs.bin", 0, "<Q", "number of rigs"),
    ("rigs.bin", 8 + 4, "<I", "number of sensors of rig 0"),
])
def test_colmap_rigs_and_frames_bin_counts_are_bounded(tmp_path, make_dataset, file, offset, fmt, what):
    """COLMAP >= 3.12 writes rigs.bin and frames.bin (the poses pycolmap takes) beside the other files; they
    were not walked, and a count patched there (or read past the end of a truncated file) had pycolmap loop
    for billions of records: now checked like the others before pycolmap reads them."""
    import struct

    sparse = _binary_model(tmp_path, make_dataset)
    raw = bytearray((sparse / file).read_bytes())
    struct.pack_into(fmt, raw, offset, (1 << 32) - 1 if fmt == "<I" else 1 << 40)
    (sparse / file).write_bytes(bytes(raw))
    with pytest.raises(InputError, match=what) as e:
        colmap.check_model(sparse)
    assert e.value.path == sparse / file


@pytest.mark.parametrize("file, change, what", [
    ("frames.bin", lambda b: b[:40], "number of frames is 4, but the file has only 32 bytes left"),
    ("rigs.bin", lambda b: b[:23], "number of sensors of rig 0 is 1, but the file has only 7 bytes left"),
    ("rigs.bin", lambda b: b + b"\0" * 5, "5 bytes after the last record"),
])
def test_colmap_truncated_or_padded_rigs_and_frames_bin_are_refused(tmp_path, make_dataset, file, change, what):
    """A truncated frames.bin hung pycolmap; a truncated or padded rigs.bin was read as if whole."""
    sparse = _binary_model(tmp_path, make_dataset)
    (sparse / file).write_bytes(bytes(change(bytearray((sparse / file).read_bytes()))))
    with pytest.raises(InputError, match=what) as e:
        colmap.check_model(sparse)
    assert e.value.path == sparse / file


@pytest.mark.parametrize("where", ["images.txt", "images.bin", "frames.bin", "frames.txt"])
def test_colmap_huge_quaternion_is_no_rotation(tmp_path, make_dataset, where):
    """A quaternion component of 1e300 raised OverflowError while its length was computed (images.txt,
    images.bin: exit 1, "a bug in splattwin"), and in frames.bin / frames.txt (COLMAP >= 3.12, where the
    poses come from) made the pose singular (LinAlgError)."""
    import struct

    import pycolmap

    if where == "frames.txt":
        sparse = _binary_model(tmp_path, make_dataset)
        rec = pycolmap.Reconstruction(str(sparse))
        for f in sparse.iterdir():
            f.unlink()
        rec.write_text(str(sparse))
        lines = (sparse / where).read_text().splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#"))
        f = lines[i].split()   # FRAME_ID RIG_ID QW QX QY QZ TX TY TZ ...
        lines[i] = " ".join(f[:2] + ["1e300"] + f[3:])
        (sparse / where).write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError, match="is not a rotation") as e:
            load_dataset(tmp_path)
        assert e.value.path == sparse   # read by pycolmap: the model folder
        return
    if where == "images.txt":
        sparse = tmp_path / "sparse" / "0"
        colmap.write_text(make_dataset(tmp_path), sparse)
        lines = (sparse / "images.txt").read_text().splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#"))
        f = lines[i].split()
        lines[i] = " ".join([f[0], "1e300"] + f[2:])
        (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    else:
        sparse = _binary_model(tmp_path, make_dataset)
        raw = bytearray((sparse / where).read_bytes())
        struct.pack_into("<d", raw, 8 + 4 + (4 if where == "frames.bin" else 0), 1e300)   # qw of the first record
        (sparse / where).write_bytes(bytes(raw))
    with pytest.raises(InputError, match="is not a rotation") as e:
        load_dataset(tmp_path)
    assert e.value.path == sparse / where


def test_colmap_binary_image_name_must_be_utf8(tmp_path, make_dataset):
    """pycolmap's Image.name raised UnicodeDecodeError (exit 1) for a name that is not UTF-8."""
    sparse = _binary_model(tmp_path, make_dataset)
    raw = (sparse / "images.bin").read_bytes()
    start = 8 + 4 + 56 + 4   # count, image id, pose, camera id: the first image's name
    end = raw.index(b"\0", start)
    (sparse / "images.bin").write_bytes(raw[:start] + b"\xff\xfe.png" + raw[end:])
    with pytest.raises(InputError, match="is not UTF-8") as e:
        load_dataset(tmp_path)
    assert e.value.path == sparse / "images.bin"


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_zero_quaternion_is_no_rotation(tmp_path, make_dataset, binary):
    """pycolmap turned a zero quaternion into the identity, silently (TUM refuses it)."""
    import struct

    if binary:
        sparse = _binary_model(tmp_path, make_dataset)
        raw = bytearray((sparse / "images.bin").read_bytes())
        struct.pack_into("<4d", raw, 8 + 4, 0.0, 0.0, 0.0, 0.0)
        (sparse / "images.bin").write_bytes(bytes(raw))
    else:
        ds = make_dataset(tmp_path)
        sparse = tmp_path / "sparse" / "0"
        colmap.write_text(ds, sparse)
        lines = (sparse / "images.txt").read_text().splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#"))
        f = lines[i].split()
        lines[i] = " ".join([f[0], "0", "0", "0", "0"] + f[5:])
        (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="is not a rotation"):
        load_dataset(tmp_path)


@pytest.mark.parametrize("mutate, msg", [
    # camera_angle_x (Blender / NeRF-synthetic): 0 divided by zero, text raised ValueError (exit 1), pi gave 5e-15 px
    (lambda m: m.update(camera_angle_x=0), "camera_angle_x must be a field of view in radians, between 0 and pi, got 0"),
    (lambda m: m.update(camera_angle_x=np.pi), "camera_angle_x must be a field of view in radians, between 0 and pi"),
    (lambda m: m.update(camera_angle_x="wide"), r"camera_angle_x \(radians\) must be a number, got str 'wide'"),
    # depth units: a bool was read as 1.0, 1e300 made every depth infinite
    (lambda m: m.update(depth_unit_scale_factor=True), "depth_unit_scale_factor must be a number, got bool"),
    (lambda m: m.update(depth_unit_scale_factor=1e300), r"depth_unit_scale_factor must be within \[1e-06, 100\]"),
    (lambda m: m.update(k1=1e300), r"distortion coefficients must be within \+-1000"),
    (lambda m: m.update(fl_x=1e308), "focal length fx = 1e\\+308 px is implausible"),
    (lambda m: m.update(cx="32"), "cx must be a number, got str '32'"),
    (lambda m: m["frames"][0]["transform_matrix"].__setitem__(3, [5, 6, 7, 8]), "must end with the row 0 0 0 1"),
    (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, 1e300), r"camera position .* more than 1e\+09 m"),
])
def test_nerfstudio_values_are_checked(tmp_path, mutate, msg, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    meta = json.loads(out.read_text())
    if "camera_angle_x" in msg:
        meta.pop("fl_x"), meta.pop("fl_y")
    mutate(meta)
    io.write_json(out, meta)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(out)
    assert e.value.path == out


@pytest.mark.parametrize("edit, msg", [
    (lambda e: e.update(id=10**400), "camera entry 0: id <an integer of about 400 digits> is too large"),
    (lambda e: e.update(id=True), "camera entry 0: id must be a number, got bool"),
    (lambda e: e.update(fx=10**400), "fx <an integer of about 400 digits> is too large"),
    (lambda e: e.update(fx="50"), "fx must be a number, got str '50'"),
    (lambda e: e.update(fx=1e308), "focal length fx = 1e\\+308 px is implausible"),
    (lambda e: e.update(position=[1e300, 0, 0]), r"position element 1 must be within \[-1e\+09, 1e\+09\]"),
    (lambda e: e.update(rotation=[["1", 0, 0], [0, 1, 0], [0, 0, 1]]), "rotation element 1 must be a number"),
])
def test_cameras_json_values_are_checked(tmp_path, make_dataset, edit, msg):
    ds = make_dataset(tmp_path, with_points=False)
    for f in ds.frames:
        f.camera.K[0, 2], f.camera.K[1, 2] = 32.0, 24.0
    out = cameras_json.write(ds, tmp_path / "cameras.json")
    cams = json.loads(out.read_text())
    edit(cams[0])
    out.write_text(json.dumps(cams))
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(out)
    assert e.value.path == out


def test_colmap_cameras_are_plausible(tmp_path, make_dataset):
    """The other readers' camera bounds hold for COLMAP models too (a focal length of 1e300 px was read)."""
    ds = make_dataset(tmp_path, with_points=False)
    sparse = tmp_path / "sparse" / "0"
    colmap.write_text(ds, sparse)
    lines = (sparse / "cameras.txt").read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#"))
    f = lines[i].split()
    f[4] = "1e300"
    lines[i] = " ".join(f)
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="focal length fx = 1e\\+300 px is implausible") as e:
        load_dataset(tmp_path)
    assert e.value.path == sparse


def test_image_folder_leaves_out_byte_identical_copies(tmp_path, caplog):
    """A copy of a photo was held out while its original trained (19 dB against 13 dB for a real held-out
    view), inflating the held-out mean without a word."""
    import logging
    import shutil

    from splattwin import io

    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        io.write_image(tmp_path / f"{name}.png", rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))
    shutil.copy(tmp_path / "b.png", tmp_path / "copy_b.png")
    with caplog.at_level(logging.WARNING):
        ds = images.read(tmp_path)
    assert [f.name for f in ds.frames] == ["a", "b", "c"]   # the first of each content is kept
    assert "1 photo is identical to another and left out" in caplog.text and "b.png" in caplog.text


def test_rig_layout_views_are_named_by_path(tmp_path, make_dataset):
    """COLMAP rig / multi-camera layout cam0/0000.png, cam1/0000.png was refused (two views named '0000');
    views are now named cam0_0000, ..., the same from COLMAP, from transforms.json and after bundling."""
    ds = make_dataset(tmp_path)
    sparse = tmp_path / "sparse" / "0"
    colmap.write_text(ds, sparse)
    rig = {f"img_{i:03d}.png": f"cam{i % 2}/{i // 2:04d}.png" for i in range(4)}
    text = (sparse / "images.txt").read_text()
    for old, new in rig.items():
        (tmp_path / "images" / new).parent.mkdir(exist_ok=True)
        (tmp_path / "images" / old).rename(tmp_path / "images" / new)
        text = text.replace(old, new)
    (sparse / "images.txt").write_text(text)
    back = load_dataset(tmp_path)
    names = ["cam0_0000", "cam1_0000", "cam0_0001", "cam1_0001"]
    assert [f.name for f in back.frames] == names
    back.frames[-1].split = "heldout"
    out = nerfstudio.write(back, tmp_path / "transforms.json")
    ns = load_dataset(out)
    assert [f.name for f in ns.frames] == names and [f.name for f in ns.heldout()] == ["cam1_0001"]
    with pytest.raises(InputError, match="view name"):    # what stays refused: a repeated path
        meta = json.loads(out.read_text())
        meta["frames"][1]["file_path"] = meta["frames"][0]["file_path"]
        out.write_text(json.dumps(meta))
        load_dataset(out)


def test_unique_stems_in_subfolders_keep_their_names(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    meta = json.loads(nerfstudio.write(ds, tmp_path / "transforms.json").read_text())
    for k, fr in enumerate(meta["frames"]):
        old = tmp_path / fr["file_path"]
        new = old.parent / f"cam{k % 2}" / old.name
        new.parent.mkdir(exist_ok=True)
        old.rename(new)
        fr["file_path"] = new.relative_to(tmp_path).as_posix()
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    assert [f.name for f in load_dataset(tmp_path).frames] == [f"img_{i:03d}" for i in range(4)]


@pytest.mark.parametrize("objects, msg", [
    ({"a/b": 1}, "label_objects name 'a/b'"),
    ({"..": 1}, "label_objects name '..'"),
    ({"": 1}, "label_objects name ''"),
    ({"box": 1, "BOX": 2}, "both give export ID"),
    ({"box": 1, "cup": 1}, "gives label id 1 to both 'box' and 'cup'"),
])
def test_transforms_json_label_objects_names_are_checked_where_they_enter(tmp_path, make_dataset, objects, msg):
    """label_objects names become the fused objects' names (semantics.lift.label_objects); a path-like, empty
    or colliding name, or two names for one label id, were taken as they were."""
    nerfstudio.write(make_dataset(tmp_path, with_points=False), tmp_path / "transforms.json")
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["label_objects"] = objects
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "transforms.json"
