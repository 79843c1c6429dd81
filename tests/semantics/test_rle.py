"""COCO RLE codec on untrusted counts: overflowing, negative, non-integer and absurdly long runs are
InputErrors, found before numpy allocates (or writes out of bounds)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.semantics import rle


def test_counts_overflowing_int64_are_refused():
    # 2**63-1 twice wraps an int64 sum to H*W; np.repeat then wrote out of bounds (a segfault), so the check
    # runs in a child process: a regression fails this test instead of killing the test run
    code = ("from splattwin.semantics import rle\n"
            "from splattwin.errors import InputError\n"
            "try:\n"
            "    rle.decode({'size': [4, 4], 'counts': [2**63 - 1, 2**63 - 1, 18]})\n"
            "except InputError as e:\n"
            "    print('refused:', e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "refused: RLE counts sum to 18446744073709551632 but the mask has 4x4=16 pixels" in r.stdout


def test_negative_and_non_integer_counts():
    with pytest.raises(InputError, match="RLE count 0 is negative .-5."):
        rle.decode({"size": [4, 4], "counts": [-5, 21]})
    for bad in (1.5, True, "3", None):
        with pytest.raises(InputError, match="whole numbers"):
            rle.decode({"size": [4, 4], "counts": [bad, 16]})
    with pytest.raises(InputError, match="runs but the mask has only"):
        rle.decode({"size": [2, 2], "counts": [0] * 10 + [4]})
    with pytest.raises(InputError, match="list of run lengths"):
        rle.decode({"size": [2, 2], "counts": 4})
    assert rle.decode({"size": [2, 2], "counts": [0, 0, 1, 3]}).sum() == 3   # zero runs are fine


def test_rle_size_must_be_a_bounded_whole_number():
    for size in ([float("inf"), 4], [4, 1e400], [4.5, 4], ["4", 4], [0, 4], [10**6, 10**6]):
        with pytest.raises(InputError, match="RLE mask (size|claims)"):
            rle.decode({"size": size, "counts": [16]})


def test_long_run_in_a_string_is_refused_without_building_it():
    # "_" is a 5-bit group with "more" set: one count of N groups was built as an N*5-bit int, quadratically
    with pytest.raises(InputError, match="run length of more than 13 characters"):
        rle.string_to_counts("_" * 20000 + "0")
    with pytest.raises(InputError, match="too long for a mask of 16 pixels"):
        rle.decode({"size": [4, 4], "counts": "_" * 20000 + "0"})
    with pytest.raises(InputError, match="outside .0, 16."):
        rle.decode({"size": [4, 4], "counts": rle.counts_to_string([100])})
    with pytest.raises(InputError, match="outside .0, 16."):
        rle.decode({"size": [4, 4], "counts": rle.counts_to_string([2, 2, 2, -1, 11])})   # a negative run
    m = np.zeros((40, 30), bool)
    m[3:30, 2:20] = True
    assert np.array_equal(rle.decode(rle.encode(m)), m)   # real counts of several groups still decode
