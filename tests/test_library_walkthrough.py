"""The README's "Using splattwin as a library" walkthrough, run as written: its python code blocks are taken from
README.md and executed in order, in one namespace, on a small twin built here from the shared `scene_small` scene
(160x120 px, 8 + 3 views; 300 iterations, ~30 s), from a folder where `my_twin` is that twin. A README edit that
breaks a call, or a change of the API it shows, fails this test; the walkthrough itself takes ~12 s."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).parents[1]
SECTION = "## Using splattwin as a library"
SMALL = {"poses": {"method": "known"}, "splat": {"iters": 300, "max_gaussians": 20000, "checkpoint_every": 0},
         "refine": {"iters": 0}}


def walkthrough_blocks(readme: str) -> list[str]:
    """The ```python blocks of the README's library section, in order."""
    start = readme.index(SECTION)
    end = readme.find("\n## ", start + len(SECTION))
    section = readme[start:end if end > 0 else None]
    return re.findall(r"```python\n(.*?)```", section, re.S)


def test_the_walkthrough_blocks_are_found():
    blocks = walkthrough_blocks((ROOT / "README.md").read_text())
    assert len(blocks) >= 6 and "Manifest.load" in blocks[1] and "run_once" in blocks[-1]


@pytest.fixture(scope="module")
def small_twin(scene_small: Path, tmp_path_factory) -> Path:
    from splattwin.pipeline.build import BuildOptions, build

    out = tmp_path_factory.mktemp("walkthrough") / "my_twin"
    build(out, BuildOptions.from_dict({"input": str(scene_small), **SMALL}), until="twin", progress=False)
    return out


def test_the_readme_walkthrough_runs_on_a_small_twin(small_twin: Path, monkeypatch):
    monkeypatch.chdir(small_twin.parent)
    ns: dict = {}
    t0 = time.perf_counter()
    for i, block in enumerate(walkthrough_blocks((ROOT / "README.md").read_text())):
        exec(compile(block, f"README.md walkthrough block {i + 1}", "exec"), ns)
    seconds = time.perf_counter() - t0
    # what each step promises, checked on what the blocks left behind
    assert ns["m"].frame.scaled and ns["m"].frame.units == "m"                           # a.
    assert 0 < ns["psnr"](ns["rgb"][0].clamp(0, 1), ns["photo"]) < 60                      # b.
    assert ns["image"].shape == (ns["cam"].height, ns["cam"].width, 3)
    labels = ns["labels"]                                                                  # c.
    assert labels.shape == (len(ns["g"]),) and set(np.unique(labels)) > {0}
    assert ns["geo"].usable and ns["geo"].visual.is_watertight                             # d.
    assert (small_twin.parent / "meshes" / "blue_box.obj").is_file() and ns["geo"].parts
    assert ns["world"].model.nbody > len(ns["m"].objects)
    assert ns["result"].success and not ns["result"].settle["moved"], (ns["result"].steps, ns["result"].settle)  # e.
    assert ns["r"].q_arm.shape == (len(ns["r"].t), 7)
    print(f"walkthrough: {seconds:.1f} s")
    assert seconds < 60, f"the walkthrough took {seconds:.0f} s"
