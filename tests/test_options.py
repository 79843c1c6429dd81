"""The options generator (`splattwin.options`): flags, config dicts and stage-key views derived from one
dataclass; and the rule that every option's default is written exactly once."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import pytest

from splattwin.errors import InputError
from splattwin.options import (add_options, dest, from_args, from_dict, load_config, option, set_everywhere, specs,
                               to_dict)

SRC = Path(__file__).parents[1] / "src" / "splattwin"


@dataclass
class Inner:
    eps: float = option(0.02, "DBSCAN eps", unit="m", aliases=("e",))
    seed: int = option(0, "seed")


@dataclass
class Toy:
    iters: int = option(3000, "steps", build_alias="iters")
    mode: str = option("a", "mode", choices=("a", "b"))
    fov: float = option(math.radians(70.0), "field of view", unit="rad", degrees=True)
    cap: int | None = option(None, "cap (none: no cap)")
    size: tuple[float, float] = option((1.0, 2.0), "size")
    on: bool = option(True, "switch")
    where: Path | None = option(None, "a file", path=True)
    workers: int | None = option(None, "processes", hashed=False)
    progress: bool = option(True, "bars", runtime=True)
    hidden: dict | None = option(None, "set from Python only", cli=False)
    inner: Inner = option(factory=Inner, help="inner options")


def _parse(argv, prefix="", build=False):
    p = argparse.ArgumentParser()
    add_options(p, Toy, prefix, build=build)
    return p.parse_args(argv)


def test_no_flags_give_the_dataclass_defaults():
    assert from_args(Toy, _parse([])) == Toy()


def test_flags_of_every_type():
    a = _parse(["--iters", "5", "--mode", "b", "--fov", "90", "--cap", "7", "--size", "3", "4", "--no-on",
                "--where", "x.yaml", "--workers", "2", "--no-progress", "--inner.eps", "0.5", "--e", "0.25"])
    t = from_args(Toy, a)
    assert (t.iters, t.mode, t.cap, t.size, t.on, t.where, t.workers, t.progress) == \
        (5, "b", 7, (3.0, 4.0), False, Path("x.yaml"), 2, False)
    assert t.fov == pytest.approx(math.pi / 2)   # the flag takes degrees, the field holds radians
    assert t.inner.eps == 0.25                    # the alias given last wins
    assert from_args(Toy, _parse(["--cap", "none"])).cap is None
    with pytest.raises(SystemExit):
        _parse(["--mode", "c"])                   # choices are checked by argparse


def test_build_flags_are_prefixed_with_short_aliases_and_no_runtime_fields():
    a = _parse(["--toy.iters", "9", "--toy.inner.seed", "3"], prefix="toy.", build=True)
    assert from_args(Toy, a, "toy.") == Toy(iters=9, inner=Inner(seed=3))
    assert from_args(Toy, _parse(["--iters", "8"], prefix="toy.", build=True), "toy.").iters == 8
    for flag in (["--toy.progress"], ["--e", "1"], ["--toy.hidden", "x"]):
        with pytest.raises(SystemExit):
            _parse(flag, prefix="toy.", build=True)


def test_help_names_unit_and_default(capsys):
    p = argparse.ArgumentParser()
    add_options(p, Toy)
    text = p.format_help()
    assert "DBSCAN eps [m] (default 0.02)" in text
    assert "field of view [deg] (default 70)" in text
    assert "switch (default on)" in text


def test_extra_spelling_of_an_option_shares_its_dest():
    p = argparse.ArgumentParser()
    add_options(p, Toy)
    p.add_argument("--fast", dest=dest("iters"), action="store_const", const=10, default=argparse.SUPPRESS)
    assert from_args(Toy, p.parse_args(["--fast"])).iters == 10


def test_dicts_round_trip_and_key_view():
    t = Toy(iters=5, where=Path("a/b.yaml"), workers=3, size=(5.0, 6.0))
    d = to_dict(t, "config")
    assert "progress" not in d and "hidden" not in d and d["size"] == [5.0, 6.0]
    assert from_dict(Toy, d) == dataclasses.replace(t, progress=True)
    key = to_dict(t, "key")
    assert "where" not in key and "workers" not in key and "progress" not in key
    assert key["inner"] == {"eps": 0.02, "seed": 0}
    assert "hidden" in to_dict(t, "record") and "progress" not in to_dict(t, "record")


def test_config_dict_errors_name_the_file_and_the_option(tmp_path):
    f = tmp_path / "c.yaml"
    with pytest.raises(InputError, match=r"unknown option 'inner.epz'") as e:
        from_dict(Toy, {"inner": {"epz": 1}}, f)
    assert str(f) in str(e.value)
    for bad, msg in (({"iters": "many"}, "iters: expected an integer"), ({"iters": True}, "expected an integer"),
                     ({"on": 1}, "true or false"), ({"size": [1]}, "a list of 2"), ({"mode": "z"}, "not one of"),
                     ({"iters": None}, "cannot be null"), ({"inner": 3}, "must be a mapping")):
        with pytest.raises(InputError, match=msg):
            from_dict(Toy, bad, f)
    assert from_dict(Toy, {"cap": None, "iters": 4, "inner": {"eps": 1}}).inner.eps == 1.0


def test_config_file_relative_paths_from_its_folder(tmp_path):
    (tmp_path / "sub").mkdir()
    f = tmp_path / "sub" / "c.yaml"
    f.write_text("where: data/x.yaml\niters: 12\ninner: {seed: 2}\n")
    t = load_config(f, Toy, base=Toy(mode="b"))
    assert t.where == tmp_path.resolve() / "sub" / "data" / "x.yaml"
    assert (t.iters, t.mode, t.inner.seed) == (12, "b", 2)
    f.write_text("iters: [1, 2\n")
    with pytest.raises(InputError, match="not valid YAML"):
        load_config(f, Toy)


def test_set_everywhere_reaches_nested_options():
    t = set_everywhere(Toy(), "seed", 7)
    assert t.inner.seed == 7
    assert set_everywhere(Toy(), "progress", False).progress is False


# -- every default is written once ------------------------------------------------------------------
def _option_classes() -> list[type]:
    from splattwin.cluster.options import BatchOptions, SweepOptions
    from splattwin.pipeline.options import BuildOptions
    from splattwin.robot.options import RobotOptions

    seen: list[type] = []

    def walk(cls):
        if cls in seen:
            return
        seen.append(cls)
        for s in specs(cls):
            if s.nested is not None:
                walk(s.nested)
    walk(BuildOptions)
    walk(RobotOptions)
    walk(SweepOptions)
    walk(BatchOptions)
    return seen


def _option_field_names() -> set[str]:
    return {s.name for cls in _option_classes() for s in specs(cls)}


def _flag_field_name(flag: str) -> str:
    name = flag.lstrip("-").rsplit(".", 1)[-1]
    return name.removeprefix("no-").replace("-", "_")


def test_no_argparse_default_repeats_an_option():
    """No `add_argument(..., default=<value>)` anywhere in the package for a flag or dest that names an
    option field: the option's default lives in its dataclass only (argparse gets none, or SUPPRESS)."""
    names = _option_field_names()
    offences = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_argument"):
                continue
            kw = {k.arg: k.value for k in node.keywords}
            default = kw.get("default")
            if default is None or (isinstance(default, ast.Constant) and default.value is None) or \
                    (isinstance(default, ast.Attribute) and default.attr == "SUPPRESS"):
                continue
            flags = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            cand = {_flag_field_name(f) for f in flags if f.startswith("--")}
            if isinstance(kw.get("dest"), ast.Constant):
                cand.add(kw["dest"].value)
            if cand & names:
                offences.append(f"{path.relative_to(SRC)}:{node.lineno} {sorted(cand & names)}")
    assert not offences, "argparse defaults that repeat an option's default: " + "; ".join(offences)


def test_every_option_has_help_and_one_home():
    """Every option field documents itself; no option dataclass is defined twice under one name (the
    hand-mirrored copies this replaced: TRAIN_DEFAULTS, BuildOptions' flat copies)."""
    classes = _option_classes()
    names = [c.__name__ for c in classes]
    assert len(names) == len(set(names))
    for cls in classes:
        for s in specs(cls):
            if s.meta.get("cli", True):
                assert s.meta.get("help"), f"{cls.__name__}.{s.name} has no help text"
    import splattwin.splat.cli as splat_cli

    assert not hasattr(splat_cli, "TRAIN_DEFAULTS")
