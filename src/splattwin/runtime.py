"""Process-wide runtime settings, applied only when asked: importing splattwin changes nothing.

`configure()` is called by the `splattwin` command (first thing in `splattwin.cli.main`), the bench
scripts and the test suite. Library users call it themselves, once, at the start of the program and
before torch, numba or mujoco are imported (two of the settings are environment variables those
libraries read when they load):

    import splattwin.runtime
    splattwin.runtime.configure()

What it sets, and why (a value the user already set is never overridden):

* ``OMP_WAIT_POLICY=PASSIVE`` (environment; libgomp reads it when it loads, i.e. on the first import
  of torch or the first numba parallel kernel). Our CPU rasterizer runs numba parallel kernels between
  small torch ops; with the default active waiting, the idle OpenMP workers of one spin on the cores the
  other needs. Measured about 2x faster training steps on 2 cores (2-3x on a loaded machine); passive
  waiting costs microseconds per kernel on an idle one.
* ``MUJOCO_GL=egl`` (environment; MuJoCo picks its OpenGL backend when it is first imported), only when
  there is no X display: headless offscreen rendering (robot frames, playback) through EGL (Mesa), where
  MuJoCo's default (GLFW) needs a display. With a display MuJoCo's own choice stands.
* numba's "TBB threading layer requires TBB version 2021 update 6" warning is silenced (a warnings filter
  on that message only). Open3D and embreex ship an older libtbb; once either is loaded, numba's first
  parallel kernel tries TBB, warns on stderr in the middle of a run's output, and uses OpenMP, which is the
  layer the settings above are tuned for. The user can do nothing about it; numba's choice is unchanged.
* numba's thread count = the CPUs this process may run on (``os.sched_getaffinity``), as
  ``NUMBA_NUM_THREADS`` before numba loads, or ``numba.set_num_threads`` after. numba's default is
  every CPU of the machine, which oversubscribes a process restricted to fewer (containers, taskset).

Thread settings that only one stage needs are scoped, not global: the trainer holds torch to one
thread for its loop with `torch_threads` and restores the previous count afterwards.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import warnings
from dataclasses import dataclass, field
from typing import Iterator

log = logging.getLogger(__name__)

TBB_WARNING = r"The TBB threading layer requires TBB version"   # numba, with Open3D's older libtbb loaded

__all__ = ["RuntimeSettings", "configure", "available_cpus", "start_numba_threads", "torch_threads",
           "peak_rss_gib"]


def peak_rss_gib() -> float:
    """This process's peak resident memory so far plus that of its waited-for children (GiB): what the
    build records per stage (TWIN/pipeline.json) and `splattwin plan` for its run."""
    import resource

    # ru_maxrss is in KiB on Linux; counts this process and waited-for children.
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return r / (1024 ** 2)


@dataclass
class RuntimeSettings:
    """What `configure` found or set. env: the variables it set (name -> value; empty when the user had
    set them all). numba_threads: numba's thread count after the call. late: settings that could not
    take effect because their library was already loaded (also logged as warnings)."""

    env: dict[str, str] = field(default_factory=dict)
    numba_threads: int = 0
    late: list[str] = field(default_factory=list)


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; all CPUs where the OS has no such mask)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def _setdefault(env: dict[str, str], name: str, value: str) -> None:
    if name not in os.environ:
        os.environ[name] = value
        env[name] = value


def configure(numba_threads: int | None = None) -> RuntimeSettings:
    """Apply the settings listed in the module docstring. Idempotent (a second call changes nothing).

    numba_threads: numba's thread count (default: `available_cpus()`; an explicit NUMBA_NUM_THREADS in
    the environment caps it)."""
    out = RuntimeSettings()
    if "OMP_WAIT_POLICY" not in os.environ and ("torch" in sys.modules or "numba" in sys.modules):
        out.late.append("OMP_WAIT_POLICY: torch/numba were imported before configure(); OpenMP may already "
                        "have read its wait policy")
    _setdefault(out.env, "OMP_WAIT_POLICY", "PASSIVE")
    warnings.filterwarnings("ignore", message=TBB_WARNING)
    if not os.environ.get("DISPLAY"):
        if "MUJOCO_GL" not in os.environ and "mujoco" in sys.modules:
            out.late.append("MUJOCO_GL: mujoco was imported before configure(); it keeps the GL backend it chose")
        _setdefault(out.env, "MUJOCO_GL", "egl")
    n = numba_threads or available_cpus()
    if "numba" in sys.modules:
        import numba

        n = max(1, min(n, numba.config.NUMBA_NUM_THREADS))
        if numba.get_num_threads() != n:
            numba.set_num_threads(n)
        out.numba_threads = numba.get_num_threads()
    else:
        _setdefault(out.env, "NUMBA_NUM_THREADS", str(n))
        out.numba_threads = int(os.environ["NUMBA_NUM_THREADS"])
    for msg in out.late:
        log.warning("splattwin.runtime.configure(): %s", msg)
    return out


_NUMBA_STARTED = False


def start_numba_threads() -> None:
    """Run one tiny numba parallel kernel, once per process. The first parallel call in a process sets the
    OpenMP thread count (numba's "omp" layer calls omp_set_num_threads), which is also torch's intra-op
    count: a torch count set before it is silently undone. torch's element-wise kernels round differently
    at their chunk boundaries with 1 and 2 threads (torch.sigmoid differs in the last bit), so the first
    training in a process ran on 2 torch threads and every later one on 1: the same run gave different
    Gaussians depending on what ran before it (`bench/train.py --repeat`, a resumed build).
    A torch count set before (`torch.set_num_threads` of the program using splattwin) is put back after it:
    the CPU rasterizer and SSIM call this before their first kernel, so a render leaves the count as it was."""
    global _NUMBA_STARTED
    if _NUMBA_STARTED:
        return
    import sys

    import numpy as np

    from splattwin._numba_start import touch

    torch = sys.modules.get("torch")   # not imported: nothing to keep (and no reason to import it here)
    before = torch.get_num_threads() if torch is not None else None
    touch(np.zeros(8))  # cached kernel: no compilation after the first run on a machine
    _NUMBA_STARTED = True
    if torch is not None and torch.get_num_threads() != before:
        torch.set_num_threads(before)


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run a block with torch's intra-op thread count set to `n`, restoring the previous count after.
    numba's thread pool is started first (`start_numba_threads`), so a numba kernel inside the block does
    not reset the count."""
    import torch

    start_numba_threads()
    before = torch.get_num_threads()
    if n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
