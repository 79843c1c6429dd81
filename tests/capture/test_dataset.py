"""Dataset helpers."""

import numpy as np


def test_resize_nearest_takes_pixel_centres():
    from splattwin.capture import resize_nearest

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    up = resize_nearest(a, 8, 6)
    assert up.shape == (6, 8) and np.array_equal(up[::2, ::2], a) and np.array_equal(up[1::2, 1::2], a)
    # down by 2: the centre of output pixel (0, 0) lies in input pixel (1, 1); values are never blended
    assert np.array_equal(resize_nearest(a, 2, 1), [[5.0, 7.0]])
    assert resize_nearest(np.zeros((5, 7, 3)), 3, 2).shape == (2, 3, 3)
