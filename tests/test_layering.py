"""The package imports only downwards: capture -> poses -> splat -> semantics -> geometry -> twin -> robot ->
playback -> report / viewer, with scene (the embedded-scene generator, used by tests and the pipeline),
pipeline, and cluster (sweeps and batches of builds) on top; the shared modules at the top level (errors, io, options, paths, ...) import no
stage. Every import counts, including those inside functions (lazy imports are still dependencies)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).parents[1] / "src" / "splattwin"

LAYERS = ["capture", "poses", "splat", "semantics", "geometry", "twin", "robot", "playback", "report", "viewer",
          "scene", "pipeline", "cluster"]
TOP = {"cli"}   # the command line registers every stage's commands


def _module(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package(path: Path) -> str:
    """The package a file's relative imports start from: the file's own module for an __init__.py, else its
    parent package."""
    me = _module(path)
    return me if path.name == "__init__.py" else me.rsplit(".", 1)[0]


def _import_nodes(path: Path, source: str | None = None) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of the file (`source` instead of its text when given), at any depth
    (functions, classes, ifs): lazy imports are dependencies too."""
    tree = ast.parse(source if source is not None else path.read_text(), str(path))
    return [node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))]


def _assert_none_in_package(check, what: str) -> None:
    """`check(path)` reports nothing for any module of the package; else the failure lists what it reported."""
    bad = [b for p in sorted(SRC.rglob("*.py")) for b in check(p)]
    assert not bad, f"{what}:\n" + "\n".join(bad)


def _imports(path: Path, source: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in the file, at any depth (`_import_nodes`)."""
    package = _package(path).split(".")
    out = []
    for node in _import_nodes(path, source):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        else:
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            # `from splattwin import io`, `from splattwin.scene import raycast`: names may be modules
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names if name == "splattwin"]
    return out


def _layer(module: str) -> str:
    """The stage package of a splattwin module, "<shared>" for the top-level modules, or "<top>"."""
    parts = module.split(".")
    if len(parts) == 1:
        return "<shared>"   # the package root (version, docstring)
    if parts[1] in LAYERS:
        return parts[1]
    return "<top>" if parts[1] in TOP else "<shared>"


def upward_imports(path: Path, source: str | None = None) -> list[str]:
    me = _layer(_module(path))
    bad = []
    for line, name in _imports(path, source):
        if name != "splattwin" and not name.startswith("splattwin."):
            continue
        them = _layer(name)
        if me == "<top>" or them == me:
            continue
        if me == "<shared>":
            ok = them == "<shared>"
        elif them == "<shared>":
            ok = True
        elif them == "<top>":
            ok = False
        else:
            ok = LAYERS.index(them) < LAYERS.index(me)
        if not ok:
            bad.append(f"{_module(path)}:{line} imports {name} ({me} may not depend on {them})")
    return bad


def test_no_upward_imports():
    _assert_none_in_package(upward_imports, "upward imports")


def test_every_stage_package_is_in_a_layer():
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert packages == set(LAYERS), f"packages not in the layering: {packages ^ set(LAYERS)}"


def test_the_checker_sees_lazy_and_relative_imports():
    """The check itself: an import inside a function, a relative import and `from splattwin import x`
    that go upwards are all reported."""
    path = SRC / "geometry" / "convert.py"
    src = ("def f():\n    from splattwin.twin.manifest import Manifest\n"
           "from ..robot import world\n"
           "from splattwin import pipeline\n"
           "from splattwin.splat.gaussians import Gaussians\n"
           "from splattwin import io\n")
    bad = upward_imports(path, src)
    assert {b.split(" imports ")[1].split(" ")[0] for b in bad} == \
        {"splattwin.twin.manifest", "splattwin.robot", "splattwin.pipeline"}
    assert upward_imports(SRC / "io.py", "from splattwin.capture import Camera\n")


def private_imports(path: Path, source: str | None = None) -> list[str]:
    """`from <another splattwin module> import _name`: a module using another's private helper (audit 10A L16).
    Private modules of the same package (`from splattwin.splat import _cpu` in splattwin.splat) are allowed:
    the underscore there marks them private to their package."""
    me, package = _module(path), _package(path)
    bad = []
    for node in _import_nodes(path, source):
        if not isinstance(node, ast.ImportFrom) or node.level or not (node.module or "").startswith("splattwin"):
            continue
        for a in node.names:
            if not a.name.startswith("_") or a.name.startswith("__") or node.module == me:
                continue
            where = SRC.parent / package.replace(".", "/") / a.name
            if node.module == package and (where.with_suffix(".py").is_file() or (where / "__init__.py").is_file()):
                continue   # a private module of its own package
            bad.append(f"{me}:{node.lineno} imports {node.module}.{a.name}")
    return bad


def test_no_module_imports_another_modules_private_names():
    _assert_none_in_package(private_imports,
                            "private names imported across modules (make them public, with a docstring)")


def test_the_private_import_checker():
    path = SRC / "splat" / "rasterize.py"
    assert private_imports(path, "from splattwin.splat import _cpu\n") == []
    assert private_imports(path, "def f():\n    from splattwin.poses.sfm import _Thing, ok\n") == \
        ["splattwin.splat.rasterize:2 imports splattwin.poses.sfm._Thing"]
