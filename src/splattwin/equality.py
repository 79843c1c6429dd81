"""Value equality for the package's plain data objects that hold numpy arrays.

A dataclass's generated `__eq__` compares its fields as tuples, and `array == array` is an array whose
truth value numpy refuses: `Gaussians.load_ply(p) == g`, `cam in cameras` raised ValueError. Such classes
set `__eq__ = dataclass_eq`: same class, and every compared field equal by value (arrays by shape and
elements, `np.array_equal`; dicts, lists and tuples item by item; nested dataclasses the same way).
Exact comparison: a float64 array saved as float32 (a 3DGS PLY) compares unequal to its original; use
`np.allclose` on the arrays for a tolerance.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


def values_equal(a: Any, b: Any) -> bool:
    """True when `a` and `b` hold the same values (arrays compared element-wise, containers recursively)."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if a is None or b is None:
            return False
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and bool(np.array_equal(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(values_equal(v, b[k]) for k, v in a.items())
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(values_equal(x, y) for x, y in zip(a, b))
    if dataclasses.is_dataclass(a) and not isinstance(a, type) and type(a) is type(b):
        return _fields_equal(a, b)
    r = a == b
    return r if isinstance(r, bool) else bool(np.all(r))


def _fields_equal(a: Any, b: Any) -> bool:
    return all(values_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.compare)


def dataclass_eq(self: Any, other: Any) -> bool:
    """`__eq__` for a dataclass with array fields: same class and every compared field equal by value."""
    if other.__class__ is not self.__class__:
        return NotImplemented
    return _fields_equal(self, other)
