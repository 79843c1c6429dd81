"""`splattwin.equality`: value equality of the plain data objects that hold arrays (audit 10A, L1).

A dataclass's generated `__eq__` compares arrays with `==` inside a tuple comparison, which numpy refuses
("truth value of an array ... is ambiguous"): `g == Gaussians.load_ply(p)` and `cam in cameras` raised."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from splattwin.equality import dataclass_eq, values_equal


@dataclass
class _Rec:
    a: np.ndarray
    d: dict = field(default_factory=dict)
    items: list = field(default_factory=list)
    note: str = field(default="", compare=False)

    __eq__ = dataclass_eq


def test_values_equal_compares_arrays_and_containers_by_value():
    assert values_equal(np.arange(3), np.arange(3.0))
    assert not values_equal(np.arange(3), np.arange(4))
    assert not values_equal(np.zeros((2, 3)), np.zeros((3, 2)))
    assert not values_equal(np.zeros(2), None) and not values_equal(None, np.zeros(2))
    assert values_equal({"x": [np.eye(2), 1]}, {"x": [np.eye(2), 1]})
    assert not values_equal({"x": [np.eye(2)]}, {"y": [np.eye(2)]})
    assert not values_equal([1, 2], (1, 2))
    assert values_equal(Path("a/b"), Path("a/b")) and not values_equal("a", "b")


def test_dataclass_eq_is_array_aware_and_unhashable():
    r = _Rec(np.arange(4), {"k": np.ones(2)}, [np.zeros(3)], note="x")
    assert r == _Rec(np.arange(4), {"k": np.ones(2)}, [np.zeros(3)], note="other")   # compare=False ignored
    assert r != _Rec(np.arange(4), {"k": np.ones(2) * 2}, [np.zeros(3)])
    assert r in [_Rec(np.arange(5)), _Rec(np.arange(4), {"k": np.ones(2)}, [np.zeros(3)])]
    assert (r == 3) is False
    with pytest.raises(TypeError):
        hash(r)
