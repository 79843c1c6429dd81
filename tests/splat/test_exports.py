"""The splat stage's public API: every name in `splattwin.splat.__all__` imports from the package."""

from __future__ import annotations

import importlib
import subprocess
import sys
import types

import pytest

import splattwin.splat as splat

KEY = ["Gaussians", "rasterization", "render", "render_rgb", "render_rgbd", "render_depth", "render_features",
       "train", "Trainer", "TrainResult", "TrainConfig", "evaluate", "EvalResult"]


def test_key_entry_points_are_listed():
    assert set(KEY) <= set(splat.__all__) and set(KEY) <= set(dir(splat))


@pytest.mark.parametrize("name", splat.__all__)
def test_each_exported_name_imports(name):
    ns: dict = {}
    exec(f"from splattwin.splat import {name}", ns)
    obj = ns[name]
    assert not isinstance(obj, types.ModuleType), name
    assert obj is getattr(importlib.import_module(f"splattwin.splat.{splat._EXPORTS[name]}"), name)


def test_no_module_shadows_an_exported_function():
    # A submodule named like an exported function would rebind the package attribute to the module
    # when imported (`import splattwin.splat.x as m` would even give the function): keep them apart.
    import pkgutil

    modules = {m.name for m in pkgutil.iter_modules(splat.__path__)}
    assert not modules & set(splat._EXPORTS), modules & set(splat._EXPORTS)
    importlib.import_module("splattwin.splat.rasterize")
    importlib.import_module("splattwin.splat.rendering")
    assert callable(splat.rasterization) and splat.rasterization.__name__ == "rasterization"
    assert callable(splat.render) and splat.render.__name__ == "render"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        splat.nope  # noqa: B018


def test_package_import_is_lazy_in_a_fresh_process():
    code = ("import sys\nimport splattwin.splat as s\nassert 'torch' not in sys.modules, 'eager torch'\n"
            "import splattwin.splat.rasterize, splattwin.splat.rendering\n"
            "from splattwin.splat import rasterization, render\n"
            "assert callable(rasterization) and rasterization.__name__ == 'rasterization'\n"
            "assert render.__name__ == 'render' and s.render is render\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
