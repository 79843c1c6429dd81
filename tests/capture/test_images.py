"""Plain image folders (`splattwin.capture.images`)."""

import numpy as np

from splattwin import io
from splattwin.capture import load_dataset
from splattwin.capture.dataset import load_image, load_loss_mask


def test_transparent_pixels_of_photos_become_loss_masks(tmp_path):
    # a photo with its background removed (alpha 0, black under it): alpha was dropped on reading and the
    # black was trained on as if the camera had seen it; now those pixels are left out as a mask_path's are
    photos = tmp_path / "photos"
    rgba = np.full((24, 32, 4), 200, np.uint8)
    rgba[:10, :, :] = 0          # transparent, black under it
    rgba[10:12, :, 3] = 128      # half transparent: an edge, still an observation
    io.write_image(photos / "a.png", rgba)
    io.write_image(photos / "b.png", np.full((24, 32, 4), 90, np.uint8)[..., :3])   # no alpha
    opaque = np.full((24, 32, 4), 90, np.uint8)
    opaque[..., 3] = 255
    io.write_image(photos / "c.png", opaque)   # alpha, none of it transparent

    ds = load_dataset(photos, frames_dir=tmp_path / "frames")
    by_name = {f.camera.name: f for f in ds.frames}
    assert by_name["b"].mask_path is None and by_name["c"].mask_path is None
    mask = by_name["a"].mask_path
    assert mask is not None and mask.is_relative_to(tmp_path / "frames")
    keep = load_loss_mask(mask, (32, 24))
    assert not keep[:10].any() and keep[10:].all()
    assert load_image(by_name["a"].image_path).shape == (24, 32, 3)   # the photo itself is read as before


def test_photos_left_in_sub_folders_are_named(tmp_path, caplog):
    # photos split over the folder and a sub-folder: the sub-folder's were left out without a word
    photos = tmp_path / "photos"
    for i, name in enumerate(("a.jpg", "b.jpg", "more/c.jpg", "more/d.jpg", "masks/a.png")):
        io.write_image(photos / name, np.full((8, 8, 3), 40 * i, np.uint8))
    with caplog.at_level("WARNING", logger="splattwin.capture.images"):
        ds = load_dataset(photos)
    assert len(ds.frames) == 2
    assert "sub-folders are not searched, so the images of more/ (2) are left out" in caplog.text
    assert "masks/" not in caplog.text   # masks beside the photos are no photos
