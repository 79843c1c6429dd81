"""bench/stages.py's profile helpers, checked on a hand-made profile."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

SRC = "/x/src/splattwin"
SITE = "/v/lib/python3.11/site-packages"
TRAIN_STEP = (f"{SRC}/splat/trainer.py", 692, "train_step")


def _profile():
    """pstats-like {(file, line, name): (primitive calls, calls, own s, cumulative s, callers)}: 10 training
    steps; the raster kernel is called 15 times (5 outside training), the SSIM kernel 10 times."""
    return SimpleNamespace(stats={
        TRAIN_STEP: (10, 10, 0.5, 10.0, {}),
        (f"{SRC}/splat/_cpu/kernels.py", 773, "raster_fwd"): (15, 15, 6.0, 6.0, {}),
        (f"{SRC}/splat/losses.py", 90, "fwd"): (10, 10, 1.0, 1.0, {}),
        ("~", 0, "<method 'acquire' of '_thread.lock' objects>"): (3, 3, 20.0, 20.0, {}),
        (f"{SITE}/numba/core/compiler.py", 1, "compile_extra"): (1, 1, 0.25, 0.3, {}),
        ("<frozen importlib._bootstrap>", 1165, "_find_and_load"): (5, 5, 0.5, 4.0, {}),
        (f"{SITE}/torch/__init__.py", 1, "<module>"): (1, 1, 0.2, 2.5, {}),
        (f"{SITE}/torch/_dynamo/__init__.py", 1, "<module>"): (1, 1, 0.1, 1.5, {}),
        (f"{SITE}/torch/utils/data.py", 1, "<module>"): (1, 1, 0.05, 0.7, {}),
        ("~", 0, "<method 'encode' of 'ImagingEncoder' objects>"): (4, 4, 0.75, 0.75, {}),
        ("~", 0, "<built-in method torch._fused_adam_>"): (60, 60, 0.6, 0.6, {}),
        (f"{SRC}/poses/table.py", 84, "fit_table_plane"): (1, 1, 0.3, 0.3, {}),
    })


def test_categories_sort_own_time_and_sum_to_the_total(load_bench):
    st = _profile()
    cats = load_bench("stages").categories(st)
    assert sum(cats.values()) == pytest.approx(sum(v[2] for v in st.stats.values()))
    assert cats["rasterizer kernels (numba)"] == pytest.approx(6.0)
    assert cats["SSIM kernels (numba)"] == pytest.approx(1.0)
    assert cats["waiting on the COLMAP worker (SfM)"] == pytest.approx(20.0)
    assert cats["numba compilation / dispatch"] == pytest.approx(0.25)
    assert cats["imports"] == pytest.approx(0.5 + 0.2 + 0.1 + 0.05)
    assert cats["image encoding / decoding (PIL)"] == pytest.approx(0.75)
    assert cats["torch operators and autograd"] == pytest.approx(0.6)
    assert cats["rest (Python, NumPy, SciPy, Open3D, ...)"] == pytest.approx(0.5 + 0.3)


def test_step_split_counts_only_the_training_share_of_kernel_calls(load_bench):
    sp = load_bench("stages").step_split(_profile())
    # raster: 10 of its 15 calls are training's -> 4.0 s; SSIM: all 10 -> 1.0 s
    assert sp == pytest.approx({"steps": 10, "total_s": 10.0, "kernels_s": 5.0, "rest_s": 5.0})
    assert load_bench("stages").step_split(SimpleNamespace(stats={})) is None


def test_library_imports_reads_each_package_init_only(load_bench):
    libs = load_bench("stages").library_imports(_profile())
    assert libs == pytest.approx({"torch": 2.5, "torch._dynamo": 1.5})   # not torch/utils/data.py
