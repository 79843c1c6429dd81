"""Importing splattwin changes nothing process-wide; `splattwin.runtime.configure()` does, explicitly.

Each check runs in a fresh interpreter: this test process has already been configured by conftest.py.
"""

from __future__ import annotations

import json
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import splattwin

SRC = str(Path(splattwin.__file__).resolve().parents[1])
# Variables configure() may set (and the one that would make MuJoCo's choice for it): cleared so the
# child starts as a user's shell would.
CLEARED = ("OMP_WAIT_POLICY", "MUJOCO_GL", "NUMBA_NUM_THREADS", "DISPLAY")


def _run(code: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in CLEARED}
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _all_modules() -> list[str]:
    """Every splattwin module (subpackages and their modules), `__main__`-style scripts excluded."""
    names = ["splattwin"]
    for m in pkgutil.walk_packages(splattwin.__path__, "splattwin."):
        names.append(m.name)
    return sorted(names)


def test_importing_every_module_changes_no_env_and_no_threads():
    modules = _all_modules()
    assert {"splattwin.splat._cpu", "splattwin.robot", "splattwin.splat.trainer", "splattwin.cli"} <= set(modules)
    code = f"""
import importlib, json, os
# the libraries splattwin builds on, loaded first: whatever they do themselves is not ours to judge
import numba, torch, mujoco, cv2, open3d  # (cv2 edits LD_LIBRARY_PATH, open3d sets TCM_ENABLE when they load)
env0, nb0, th0, inter0 = dict(os.environ), numba.get_num_threads(), torch.get_num_threads(), torch.get_num_interop_threads()
failed = []
for name in {modules!r}:
    try:
        importlib.import_module(name)
    except ImportError as e:   # an optional dependency (e.g. gsplat) that is not installed
        failed.append(name)
env1 = dict(os.environ)
print(json.dumps({{"added": sorted(set(env1) - set(env0)), "removed": sorted(set(env0) - set(env1)),
                  "changed": sorted(k for k in env0 if k in env1 and env0[k] != env1[k]),
                  "numba": [nb0, numba.get_num_threads()], "torch": [th0, torch.get_num_threads()],
                  "interop": [inter0, torch.get_num_interop_threads()], "failed": failed,
                  "loaded": sum(n in __import__("sys").modules for n in {modules!r})}}))
"""
    r = _run(code)
    assert r["loaded"] >= len(modules) - len(r["failed"]) and r["loaded"] > 100
    assert r["added"] == [] and r["removed"] == [] and r["changed"] == [], r
    assert r["numba"][0] == r["numba"][1] and r["torch"][0] == r["torch"][1] and r["interop"][0] == r["interop"][1]


def test_plain_import_changes_no_env():
    r = _run("import json, os\nenv0 = dict(os.environ)\nimport splattwin, splattwin.splat, splattwin.robot, "
             "splattwin.semantics, splattwin.geometry, splattwin.twin, splattwin.cli\n"
             "print(json.dumps({'same': dict(os.environ) == env0}))")
    assert r["same"]


def test_configure_sets_documented_values_once_and_respects_the_user():
    code = """
import json, os
import splattwin.runtime as rt
a = rt.configure()
env1 = {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "MUJOCO_GL", "NUMBA_NUM_THREADS")}
b = rt.configure()                       # idempotent: nothing more to set
import numba
print(json.dumps({"env": env1, "set_first": a.env, "set_second": b.env, "late": a.late + b.late,
                  "numba": numba.get_num_threads(), "cpus": rt.available_cpus()}))
"""
    r = _run(code)
    assert r["env"]["OMP_WAIT_POLICY"] == "PASSIVE" and r["env"]["MUJOCO_GL"] == "egl"
    assert r["env"]["NUMBA_NUM_THREADS"] == str(r["cpus"]) and r["numba"] == r["cpus"]
    assert set(r["set_first"]) == {"OMP_WAIT_POLICY", "MUJOCO_GL", "NUMBA_NUM_THREADS"}
    assert r["set_second"] == {} and r["late"] == []
    # a user's own choice wins, a display keeps MuJoCo's default, and loading torch first is reported
    r = _run("import json, os\nos.environ.update(OMP_WAIT_POLICY='ACTIVE', DISPLAY=':0')\nimport torch\n"
             "import splattwin.runtime as rt\ns = rt.configure()\n"
             "print(json.dumps({'omp': os.environ['OMP_WAIT_POLICY'], 'gl': os.environ.get('MUJOCO_GL'), "
             "'set': s.env, 'late': s.late}))")
    assert r["omp"] == "ACTIVE" and r["gl"] is None and "OMP_WAIT_POLICY" not in r["set"] and r["late"] == []
    r = _run("import json\nimport torch\nimport splattwin.runtime as rt\ns = rt.configure()\n"
             "print(json.dumps({'late': s.late}))")
    assert len(r["late"]) == 1 and "OMP_WAIT_POLICY" in r["late"][0]


def test_no_tbb_warning_in_a_run_that_loads_open3d_first():
    """Open3D's libtbb is older than numba's TBB layer wants: numba warned on stderr mid-run, then used
    OpenMP. configure() silences that message only; the layer stays OpenMP."""
    code = """
import json{cfg}
import open3d, numba, numpy as np
@numba.njit(parallel=True)
def total(a):
    s = 0.0
    for i in numba.prange(len(a)):
        s += a[i]
    return s
print(json.dumps({{"sum": total(np.ones(1000)), "layer": numba.threading_layer()}}))
"""
    env = {k: v for k, v in os.environ.items() if k not in CLEARED}
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    runs = {}
    for name, cfg in (("plain", ""), ("configured", "\nimport splattwin.runtime as rt\nrt.configure()")):
        r = subprocess.run([sys.executable, "-c", code.format(cfg=cfg)], env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
        runs[name] = (json.loads(r.stdout.strip().splitlines()[-1]), r.stderr)
    assert runs["plain"][0] == runs["configured"][0] and runs["plain"][0]["sum"] == 1000.0   # same layer
    # (with open3d-cpu 0.19's libtbb the plain run prints the warning; a later Open3D may not)
    assert "TBB threading layer" not in runs["configured"][1]


def test_configure_after_numba_sets_its_threads():
    r = _run("import json\nimport numba\nnumba.set_num_threads(1)\nimport splattwin.runtime as rt\n"
             "s = rt.configure(numba_threads=2)\n"
             "print(json.dumps({'n': numba.get_num_threads(), 'max': numba.config.NUMBA_NUM_THREADS, 'report': s.numba_threads}))")
    assert r["n"] == min(2, r["max"]) == r["report"]


def test_torch_threads_is_scoped():
    import torch

    from splattwin.runtime import torch_threads

    before = torch.get_num_threads()
    want = 1 if before != 1 else 2
    try:
        with torch_threads(want):
            assert torch.get_num_threads() == want
            raise KeyError("leaves the block by an exception")
    except KeyError:
        pass
    assert torch.get_num_threads() == before


def test_torch_threads_survive_the_first_numba_kernel():
    # the first numba parallel call in a process sets OpenMP's thread count, torch's too; torch_threads
    # starts numba's pool first, so the count set for the block holds (without it: 2 inside the block)
    out = _run(
        "import json, splattwin.runtime as r; r.configure(numba_threads=2)\n"
        "import numpy as np, torch\n"
        "from numba import njit, prange\n"
        "@njit(parallel=True)\n"
        "def k(a):\n"
        "    for i in prange(a.shape[0]):\n"
        "        a[i] += 1.0\n"
        "torch.set_num_threads(2)\n"
        "with r.torch_threads(1):\n"
        "    k(np.zeros(64))\n"
        "    inside = torch.get_num_threads()\n"
        "print(json.dumps({'inside': inside, 'after': torch.get_num_threads()}))\n")
    assert out == {"inside": 1, "after": 2}



@pytest.mark.parametrize("first", ["render", "ssim"])
def test_a_render_and_the_ssim_loss_keep_the_callers_torch_thread_count(first):
    """A notebook's torch.set_num_threads(1) became 2 after its first CPU render: numba's first parallel kernel
    set OpenMP's thread count, torch's too (api13 B1). The CPU rasterizer and the SSIM loss (each the first
    numba kernel of its process here) start numba's pool first, and that start puts the torch count back."""
    calls = {"render": "render_rgb(g, cam, backend='cpu')",
             "ssim": "fused_ssim(torch.rand(24, 32, 3), torch.rand(24, 32, 3))"}
    out = _run(
        "import json, splattwin.runtime as r; r.configure()\n"
        "import numpy as np, torch\n"
        "torch.set_num_threads(1)\n"
        "from splattwin.capture import Camera, look_at\n"
        "from splattwin.splat import Gaussians, render_rgb\n"
        "from splattwin.splat.losses import fused_ssim\n"
        "n = 32\n"
        "g = Gaussians(np.random.default_rng(0).normal(0, 0.05, (n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),\n"
        "              np.full((n, 3), 0.01), np.full(n, 0.8), np.full((n, 1, 3), 0.5))\n"
        "cam = Camera.from_fov(1.0, 32, 24, look_at(np.array([0.5, 0.0, 0.3]), np.zeros(3)))\n"
        "before = torch.get_num_threads()\n"   # (read: torch's pool is set up; unread, the render kept 1 before)
        f"{calls[first]}\n"
        "print(json.dumps({'before': before, 'after': torch.get_num_threads()}))\n")
    assert out == {"before": 1, "after": 1}
