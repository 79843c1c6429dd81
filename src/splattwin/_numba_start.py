"""One tiny numba parallel kernel, compiled once and cached on disk (`cache=True`), that
`splattwin.runtime.start_numba_threads` runs to start numba's thread pool. Kept in its own module so that
importing `splattwin.runtime` never imports numba."""

from __future__ import annotations

from numba import njit, prange


@njit(parallel=True, cache=True)
def touch(a):
    for i in prange(a.shape[0]):
        a[i] = i
