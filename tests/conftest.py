"""Shared pytest fixtures for every stage.

Scene fixtures (session-scoped, generated lazily on first use into a temporary folder, return the scene
directory `Path`; layout in docs/CONTRACTS.md "Embedded scene"):
- `scene_small`:   160x120, 8 training + 3 held-out views, no marker (fast: use it unless you need more)
- `scene_default`: 320x240, 15 + 5 views, no marker (the default `splattwin scene generate`)
- `scene_marker`:  320x240, 15 + 5 views, ArUco marker (DICT_4X4_50 id 0, 0.08 m) on the table
All use seed 0. Treat them as read-only: they are shared by every test of the session.

Real captures (read in place, never copied into the repo): `REAL` is the folder of /work/shared/data/real
(or $SPLATTWIN_REAL_DATA; fixture `real_data`), `CAKE` the cake photos' folder (`cake_images`); both skip the
test where the data is missing. `cake_sfm` (session): (SfM work dir, the unscaled
PoseResult, its saved poses folder) of one default SfM run on the cake (~1 min), shared by
tests/poses/test_sfm_real.py and tests/pipeline/test_unscaled_real.py; read-only (a test that resumes a pose
run writes into the work dir: copy it first).

`test_module`: a test file's helpers as a module (`test_module("splat/test_trainer.py").make_dataset(...)`).

`terminal_ctrl_c`: SIGINT handled as in an interactive terminal for the test (and so in the child processes
it starts), whatever the test run inherited.
"""

from __future__ import annotations

import importlib.util
import os
import signal
from pathlib import Path

import pytest

import splattwin.runtime

# As the CLI does, before any test module imports torch, numba or mujoco (tests/test_runtime.py checks
# that importing splattwin alone changes nothing).
splattwin.runtime.configure()


REAL = Path(os.environ.get("SPLATTWIN_REAL_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "real"))
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real")
CAKE = REAL / "cake" / "images"


def _make_scene(tmp_path_factory: pytest.TempPathFactory, name: str, **kw) -> Path:
    from splattwin.scene import SceneOptions, generate

    out = tmp_path_factory.mktemp(name)
    return generate(out, SceneOptions(seed=0, **kw), progress=False)


@pytest.fixture(scope="session")
def scene_small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """160x120, 8 training + 3 held-out views, seed 0, no marker."""
    return _make_scene(tmp_path_factory, "scene_small", width=160, height=120, views=8, heldout=3)


@pytest.fixture(scope="session")
def scene_default(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """320x240, 15 training + 5 held-out views, seed 0, no marker."""
    return _make_scene(tmp_path_factory, "scene_default", width=320, height=240, views=15, heldout=5)


@pytest.fixture(scope="session")
def scene_marker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """320x240, 15 training + 5 held-out views, seed 0, ArUco marker id 0 (0.08 m) on the table."""
    return _make_scene(tmp_path_factory, "scene_marker", width=320, height=240, views=15, heldout=5,
                       marker=True)


@pytest.fixture
def terminal_ctrl_c():
    """SIGINT raises KeyboardInterrupt in this process for the test, as in an interactive terminal; a child
    process started meanwhile gets the default disposition (a handled signal is reset on exec), so its
    Python does the same. A test run started in the background of a script (`make test &`) inherits
    SIGINT *ignored*: Python then never sees a Ctrl-C and splattwin rightly leaves an ignored SIGINT
    ignored, so the Ctrl-C tests would fail without testing anything."""
    prev = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, prev)


@pytest.fixture(scope="session")
def test_module():
    """path under tests/ -> that test file loaded as a module, once per session (its helpers: datasets,
    twin folders), for tests of other stages that build the same inputs."""
    root = Path(__file__).resolve().parent
    cache: dict = {}

    def load(rel: str):
        if rel not in cache:
            name = "_helpers_" + rel.replace("/", "_").removesuffix(".py")
            spec = importlib.util.spec_from_file_location(name, root / rel)
            mod = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(mod)
            cache[rel] = mod
        return cache[rel]

    return load


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The real captures' folder (skips the test where it is missing)."""
    if not REAL.is_dir():
        pytest.skip(f"real captures not available at {REAL}")
    return REAL


@pytest.fixture(scope="session")
def cake_images(real_data: Path) -> Path:
    """The cake photos' folder (8 frames, 683x384; skips the test where it is missing)."""
    if not CAKE.is_dir():
        pytest.skip(f"real captures not available at {CAKE}")
    return CAKE


@pytest.fixture(scope="session")
def cake_sfm(cake_images: Path, tmp_path_factory: pytest.TempPathFactory):
    """(work dir with the finished SfM model, the unscaled PoseResult, its saved poses folder) of
    `estimate_poses(load_dataset(cake_images), PoseOptions(work_dir=..., progress=False))`, run once per
    session. Read-only: copy the work dir before resuming a pose run in it, save elsewhere."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    tmp = tmp_path_factory.mktemp("cake_sfm")
    work = tmp / "sfm"
    res = estimate_poses(load_dataset(cake_images), PoseOptions(work_dir=work, progress=False))
    res.save(tmp / "poses")
    return work, res, tmp / "poses"
