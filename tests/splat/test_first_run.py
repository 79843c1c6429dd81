"""The CPU kernels' first compile after install is said once, and not when numba's cache has them
(`splattwin.splat._cpu.first_run`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import splattwin
from splattwin.splat._cpu.first_run import MESSAGE

SRC = str(Path(splattwin.__file__).resolve().parents[1])

# A fresh process that compiles a function of its own (not ours: no message), then calls one kernel of the
# rasterizer twice. `_levels` is the module's smallest kernel (~0.1 s to compile; all of them take ~40 s):
# which kernel compiles does not matter to the notice, only that the cache missed.
_CHILD = """
import logging, sys
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
from numba import njit
from splattwin.splat._cpu import K_
njit(lambda x: x + 1)(1)
print("MARK", file=sys.stderr, flush=True)
K_._levels(0.5)
K_._levels(0.25)
"""


def _run(env_extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "NUMBA_CACHE_LOCATOR_CLASSES")}
    env.update(env_extra, PYTHONPATH=SRC + os.pathsep + env.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stderr


@pytest.mark.parametrize("where", ["NUMBA_CACHE_DIR", "user-wide"])
def test_first_compile_is_said_once_and_not_with_a_warm_cache(tmp_path, where):
    # NUMBA_CACHE_DIR: the user's own cache folder; user-wide: where numba caches for a read-only
    # site-packages install (~/.cache/numba, here under $XDG_CACHE_HOME)
    env = ({"NUMBA_CACHE_DIR": str(tmp_path)} if where == "NUMBA_CACHE_DIR" else
           {"NUMBA_CACHE_LOCATOR_CLASSES": "UserWideCacheLocator", "XDG_CACHE_HOME": str(tmp_path)})
    cold = _run(env)
    assert cold.count(MESSAGE) == 1, cold[-3000:]
    assert cold.index("MARK") < cold.index(MESSAGE)   # not for a numba function of another module
    assert list(tmp_path.rglob("kernels._levels-*.nbi")), "the kernel was not cached where expected"
    warm = _run(env)                                   # the same cache: the kernel loads, nothing is said
    assert MESSAGE not in warm, warm[-3000:]


# In a fresh process: `warm()`, then a CPU training (SH degree 1, as the defaults) and an eval; prints the
# kernel signatures those added after warm() (each would have been a compile that warm() left to them).
_AFTER_WARM = """
import json, sys
from numba.core.dispatcher import Dispatcher
from splattwin.cli import main
from splattwin.splat import losses
from splattwin.splat._cpu import K_
from splattwin.splat._cpu.first_run import warm

def signatures():
    disp = {n: d for n, d in vars(K_).items() if isinstance(d, Dispatcher)}
    disp.update(zip(("ssim_fwd", "ssim_bwd"), losses._kernels()))
    return {n: {str(s) for s in d.overloads} for n, d in disp.items()}

warm(progress=False)
before = signatures()
ds, out = sys.argv[1], sys.argv[2]
assert main(["train", ds, out, "--iters", "3", "--no-progress", "--device", "cpu"]) == 0
assert main(["eval", out, "--dataset", ds, "--no-progress", "--device", "cpu"]) == 0
after = signatures()
print(json.dumps({n: sorted(after[n] - before.get(n, set())) for n in after if after[n] - before.get(n, set())}))
"""


def test_warm_compiles_every_kernel_training_and_eval_call(tmp_path):
    """`python -m splattwin.splat._cpu --warm` (run by `make venv`) leaves no kernel for the first training or
    evaluation to compile: after warm(), they call no kernel with a signature warm() did not."""
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
    helpers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    ds = helpers.make_dataset(tmp_path / "ds", n_train=4, n_heldout=1)
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, "-c", _AFTER_WARM, str(ds), str(tmp_path / "out")], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {}


def test_warm_command(capsys):
    from splattwin.splat._cpu.__main__ import main

    assert main(["--warm", "--no-progress"]) == 0
    assert "CPU kernels ready in" in capsys.readouterr().out
