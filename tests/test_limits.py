"""splattwin.limits: bounded readers give an InputError naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.errors import InputError


def test_yaml_long_integer_names_the_file(tmp_path):
    """Python refuses integers of more than 4300 digits with a ValueError that load_yaml let through
    (a task YAML gave an internal error, exit 1)."""
    from splattwin.limits import load_yaml

    p = tmp_path / "task.yaml"
    p.write_text("n: " + "7" * 5000 + "\n")
    with pytest.raises(InputError, match="number too long to read") as e:
        load_yaml(p)
    assert e.value.path == p and len(str(e.value)) < 300


def test_yaml_key_given_twice_is_refused_but_a_merge_may_be_overridden(tmp_path):
    """YAML's loaders keep the last of two equal keys silently (a task giving `goal` twice used the second);
    JSON readers already refuse duplicates. Keys a merge (<<: *base) brings in may still be overridden."""
    from splattwin.limits import load_yaml, loads_yaml

    p = tmp_path / "task.yaml"
    p.write_text("steps:\n  - {pick: cube, place: box, pick: hammer}\n")
    with pytest.raises(InputError, match=r"key 'pick' is given twice \(line 2\)") as e:
        load_yaml(p)
    assert e.value.path == p
    with pytest.raises(InputError, match="'a' is given twice"):
        loads_yaml("a: 1\nb: 2\na: 3\n", "x.yaml")
    assert loads_yaml("base: &b {x: 1, y: 2}\nd:\n  <<: *b\n  x: 5\n") == {"base": {"x": 1, "y": 2},
                                                                          "d": {"x": 5, "y": 2}}
    assert loads_yaml("a: {x: 1}\nb: {x: 1}\n") == {"a": {"x": 1}, "b": {"x": 1}}  # same key, other maps


def test_trajectory_yaml_is_read_with_the_bounded_loader(tmp_path):
    """A received trajectory.ros2.yaml went through yaml.safe_load: an alias bomb expanded without bound."""
    from splattwin.robot.trajectory import Trajectory

    p = tmp_path / "trajectory.ros2.yaml"
    lines = ["a0: &a0 [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    lines += ["joint_names: [j1]", "points: *a8"]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="aliases") as e:
        Trajectory.load_ros2_yaml(p)
    assert e.value.path == p


def test_16_bit_greyscale_photos_are_scaled_not_clipped(tmp_path):
    """A mono16 frame (machine-vision and ROS cameras) was converted by PIL's clipping: every pixel above 255
    of 65535 became white, and the capture trained on white images (12 dB, exit 0, no warning)."""
    from PIL import Image

    from splattwin.capture.dataset import load_image

    ramp = (np.linspace(0, 65535, 64 * 48).reshape(48, 64)).astype(np.uint16)
    p = tmp_path / "mono16.png"
    Image.fromarray(ramp).save(p)
    assert Image.open(p).mode.startswith("I")
    img = load_image(p)
    assert img.shape == (48, 64, 3) and np.allclose(img[..., 0], img[..., 2])
    np.testing.assert_allclose(img[..., 0], ramp / 65535.0, atol=1 / 255)
    assert 0.4 < img.mean() < 0.6   # clipped, it read 1.0 nearly everywhere
    Image.fromarray(ramp.astype(np.float32)).save(tmp_path / "f.tif")
    with pytest.raises(InputError, match="float image") as e:
        load_image(tmp_path / "f.tif")
    assert e.value.path == tmp_path / "f.tif"


def test_size_text_keeps_sizes_apart():
    """A file just over its limit must not read as the limit itself (it read "0 MiB, more than the limit of
    0 MiB" for small limits, and "1 MiB ... of 1 MiB" for 1.4 MiB against 1 MiB)."""
    from splattwin.limits import size_text

    assert size_text(16) == "16 bytes"
    assert size_text(1536) == "1.5 KiB"
    assert size_text(int(1.4 * 2**20)) == "1.4 MiB" and size_text(2**20) == "1.0 MiB"
    assert size_text(3 * 2**30) == "3.0 GiB" and size_text(5 * 2**40) == "5120.0 GiB"
