"""Dataset helpers."""

import numpy as np
import pytest

from splattwin.capture import load_dataset
from splattwin.errors import InputError


def test_resize_nearest_takes_pixel_centres():
    from splattwin.capture import resize_nearest

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    up = resize_nearest(a, 8, 6)
    assert up.shape == (6, 8) and np.array_equal(up[::2, ::2], a) and np.array_equal(up[1::2, 1::2], a)
    # down by 2: the centre of output pixel (0, 0) lies in input pixel (1, 1); values are never blended
    assert np.array_equal(resize_nearest(a, 2, 1), [[5.0, 7.0]])
    assert resize_nearest(np.zeros((5, 7, 3)), 3, 2).shape == (2, 3, 3)


def test_truncated_or_corrupt_images_are_refused_cheaply(tmp_path):
    """`limits.check_image_complete` (run by `Dataset.validate`): complete JPEG/PNG pass on their end marker;
    a cut-short one is refused naming the file; data after a JPEG's end (a motion photo's video) is fine."""
    from PIL import Image

    from splattwin.limits import check_image_complete

    rng = np.random.default_rng(0)
    arr = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    for suffix in (".jpg", ".png"):
        good = tmp_path / f"good{suffix}"
        Image.fromarray(arr).save(good)
        check_image_complete(good)
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(good.read_bytes()[: good.stat().st_size * 2 // 3])
        with pytest.raises(InputError, match="truncated or corrupt") as e:
            check_image_complete(cut)
        assert e.value.path == cut
    trailer = tmp_path / "motion.jpg"
    trailer.write_bytes((tmp_path / "good.jpg").read_bytes() + b"\0\0ftypmp42" + bytes(100))
    check_image_complete(trailer)
    # an image folder with a cut-short photo is refused when loaded (before any SfM)
    folder = tmp_path / "cap"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(arr).save(folder / f"{i}.jpg")
    (folder / "1.jpg").write_bytes((folder / "1.jpg").read_bytes()[:400])
    with pytest.raises(InputError, match="truncated") as e:
        load_dataset(folder)
    assert str(folder / "1.jpg") in str(e.value)


def test_links_out_of_a_posed_dataset_are_refused_but_a_photo_folder_of_links_is_read(tmp_path):
    """A transforms.json dataset may come from someone else: an image that is a link out of its folder is
    refused (`splattwin.paths.confined`). A plain photo folder is the user's own capture: links are read,
    and named by the link, not the target."""
    import json
    import os

    from PIL import Image

    photo = tmp_path / "elsewhere" / "IMG_1234.png"
    photo.parent.mkdir()
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(photo)
    ds_dir = tmp_path / "dataset"
    (ds_dir / "images").mkdir(parents=True)
    os.symlink(photo, ds_dir / "images" / "a.png")
    (ds_dir / "transforms.json").write_text(json.dumps({
        "fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48,
        "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(InputError, match="leads outside its folder"):
        load_dataset(ds_dir)
    ds = load_dataset(ds_dir / "images")  # the same folder given as a photo folder
    assert [f.image_path for f in ds.frames] == [ds_dir / "images" / "a.png"] and ds.frames[0].name == "a"


def test_linked_photos_are_named_by_their_links_and_bundled_as_files(tmp_path):
    """Links to photos in several folders: SfM names and bundled names are the links' (not `a/IMG_1.png`, nor
    paths relative to `/` when the targets share no folder), and the bundle holds files, not links."""
    import os

    from PIL import Image

    from splattwin.capture import Camera
    from splattwin.capture.bundle import bundle_frames
    from splattwin.capture.dataset import Frame
    from splattwin.poses.sfm import image_layout

    cap = tmp_path / "cap"
    cap.mkdir()
    frames = []
    for i, sub in enumerate(("a", "b")):
        target = tmp_path / "elsewhere" / sub / f"IMG_{i}.png"
        target.parent.mkdir(parents=True)
        Image.fromarray(np.full((48, 64, 3), 40 * i, np.uint8)).save(target)
        os.symlink(target, cap / f"view{i}.png")
        frames.append(Frame(image_path=cap / f"view{i}.png", camera=Camera.from_fov(1.0, 64, 48, name=f"view{i}")))
    assert image_layout([f.image_path for f in frames]) == (cap.resolve(), ["view0.png", "view1.png"])
    out = tmp_path / "out"
    bundled = bundle_frames(frames, out)
    for f, b in zip(frames, bundled):
        assert b.image_path == out / "images" / f.image_path.name
        assert not b.image_path.is_symlink() and b.image_path.read_bytes() == f.image_path.read_bytes()


def test_datasets_compare_by_value(scene_small):
    """`Dataset == Dataset` raised ValueError (cameras' and points' arrays); audit 10A L1."""
    a, b = load_dataset(scene_small), load_dataset(scene_small)
    assert a == b and a.frames[0] == b.frames[0] and a.frames[0] in b.frames
    b.frames[1].camera.T_world_cam[0, 3] += 0.01
    assert a != b


def test_a_folder_whose_images_are_in_sub_folders_names_them(tmp_path):
    # a RealSense / ROS export without a pose list (rgb/ + depth/), or one folder per camera: "no dataset found"
    # alone sent the user looking for what was wrong with their photos
    from splattwin import io

    for sub, n in (("depth", 3), ("rgb", 3), ("notes", 0), (".thumbnails", 2)):
        (tmp_path / sub).mkdir()
        for i in range(n):
            io.write_image(tmp_path / sub / f"{i:04d}.png", np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(InputError) as e:
        load_dataset(tmp_path)
    msg = str(e.value)
    assert "no dataset found here" in msg and "depth/ (3 images), rgb/ (3 images)." in msg
    assert "notes/" not in msg and ".thumbnails" not in msg
    assert f"e.g. {tmp_path / 'rgb'}" in msg


def test_hidden_files_beside_the_photos_are_left_out(tmp_path):
    # macOS's AppleDouble `._IMG.JPG` beside every photo copied to an exFAT drive: no image, and the whole
    # capture stopped on it as unreadable
    from splattwin import io

    for i in range(3):
        io.write_image(tmp_path / f"IMG_{i}.JPG", np.full((8, 8, 3), 40 * i, np.uint8))
        (tmp_path / f"._IMG_{i}.JPG").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        ")
    ds = load_dataset(tmp_path)
    assert [f.image_path.name for f in ds.frames] == ["IMG_0.JPG", "IMG_1.JPG", "IMG_2.JPG"]


def test_repeated_view_names_are_refused_before_any_image_is_read(tmp_path, make_dataset, monkeypatch):
    """A transforms.json listing its 4 images 500 times: the repeated view names need no file to find, but
    they were checked only after validate() had read every frame's image header and end (~3 ms a frame: a
    minute for 20 000 frames). Now the names are checked first."""
    import json

    from splattwin.capture import nerfstudio
    from splattwin.capture.dataset import Dataset

    nerfstudio.write(make_dataset(tmp_path, with_points=False), tmp_path / "transforms.json")
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["frames"] = meta["frames"] * 500
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    validated = []
    monkeypatch.setattr(Dataset, "validate", lambda self: validated.append(len(self.frames)))
    with pytest.raises(InputError, match="two images have the view name 'img_000'"):
        load_dataset(tmp_path)
    assert validated == []
