"""BuildOptions nests the stages' options: every stage option is reachable from `build`/`demo` flags and
from a config file, flags override the file, and each stage's key follows its own sub-config only."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

from splattwin.cli import build_parser, main
from splattwin.errors import InputError
from splattwin.options import Spec, is_option, specs, to_dict
from splattwin.pipeline.cli import resolve_options
from splattwin.pipeline.options import BuildOptions


def _leaves(cls, prefix=""):
    """(dotted path, Spec) of every option a config file / build flag can set."""
    for s in specs(cls):
        if not is_option(s):
            continue
        if s.nested is not None:
            yield from _leaves(s.nested, f"{prefix}{s.name}.")
        else:
            yield f"{prefix}{s.name}", s


# free-text options whose values are checked: a valid value other than the default
_VALID_TEXT = {"urdf_uri": "file", "moveit_frame": "robot_world", "joint_names": "fr3"}


def _other_value(s: Spec):
    """A valid value other than the default, and its command-line form."""
    if s.name in _VALID_TEXT:
        return _VALID_TEXT[s.name], [_VALID_TEXT[s.name]]
    d = s.default()
    choices = s.meta.get("choices")
    if choices:
        v = next(c for c in choices if c != d)
        return v, [str(v)]
    if s.base is bool:
        return (not d), None
    if s.base is int:
        v = (d or 0) + 2
        return v, [str(v)]
    if s.base is float:
        v = (d or 0.0) + 0.25
        if s.meta.get("degrees"):
            import math

            return math.radians(33.0), ["33"]
        return v, [repr(v)]
    if s.base is tuple:
        v = tuple(type(x)(x + 1) for x in d)
        return v, [str(x) for x in v]
    if s.base is Path:
        return Path("some/file.yaml"), ["some/file.yaml"]
    return "other-value", ["other-value"]


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def test_build_options_nest_and_do_not_copy():
    stage_fields = {s.name for s in specs(BuildOptions)} - {"input"}
    nested_names = set()
    for s in specs(BuildOptions):
        if s.name != "input":
            assert s.nested is not None, f"BuildOptions.{s.name} must be a stage's options dataclass"
            nested_names |= {x.name for x in specs(s.nested)}
    assert not (stage_fields | {"input"}) & nested_names, "BuildOptions repeats a stage option"
    assert "extra" not in {s.name for s in specs(BuildOptions)}


@pytest.mark.parametrize("command", ["build", "demo"])
def test_every_stage_option_is_a_flag(command):
    parser = build_parser()
    base = ["build", "data", "--out", "t"] if command == "build" else ["demo"]
    n = 0
    for path, s in _leaves(BuildOptions):
        if path == "input" or (command == "build" and path.startswith("scene.")):
            continue
        value, text = _other_value(s)
        flag = "--" + ".".join(p.replace("_", "-") for p in path.split(".")[:-1] + [s.meta.get("flag") or s.name])
        if s.base is bool:
            argv = [flag] if value else ["--no-" + flag[2:]]
        else:
            argv = [flag, *text]
        opts = resolve_options(parser.parse_args(base + argv), demo=command == "demo")
        got = _get(opts, path)
        assert got == pytest.approx(value) if isinstance(value, float) else got == value, (path, got, value)
        n += 1
    assert n > 120   # every stage's options, not a handful


def test_short_aliases_and_seed():
    p = build_parser()
    o = resolve_options(p.parse_args(["build", "data", "--out", "t", "--iters", "80", "--kappa", "2", "--task",
                                      "default", "--no-frames", "--poses", "sfm", "--seed", "4",
                                      "--splat.seed", "9"]))
    assert (o.splat.iters, o.semantics.fusion.kappa, o.robot.task, o.robot.render, o.poses.method) == \
        (80, 2.0, "default", False, "sfm")
    assert (o.poses.seed, o.robot.seed, o.geometry.seed, o.splat.seed) == (4, 4, 4, 9)   # the flag wins
    # the scale and intrinsics flags the messages name (the unscaled-twin warning, plan's refusal, SfM's
    # advice) are build flags too: `build --known-length` was an unrecognized argument
    k = resolve_options(p.parse_args(["build", "data", "--out", "t", "--known-length", "camera_height=0.4",
                                      "--intrinsics", "500,500,320,240"]))
    assert (k.poses.known_length, k.poses.intrinsics) == ("camera_height=0.4", "500,500,320,240")
    d = resolve_options(p.parse_args(["demo", "--views", "6", "--width", "96"]), demo=True)
    assert (d.scene.views, d.scene.width, d.poses.method, d.robot.task) == (6, 96, "known", "default")
    # the demo trains antialiased and refines its objects; build does neither unless asked; flags win
    assert (d.splat.rasterize_mode, d.refine.iters) == ("antialiased", 800)
    b = resolve_options(p.parse_args(["build", "data", "--out", "t"]))
    assert (b.splat.rasterize_mode, b.refine.iters) == ("classic", 0)
    d = resolve_options(p.parse_args(["demo", "--refine.iters", "0", "--splat.rasterize-mode", "classic"]), demo=True)
    assert (d.splat.rasterize_mode, d.refine.iters) == ("classic", 0)
    assert resolve_options(p.parse_args(["build", "data", "--out", "t"])) == BuildOptions(input="data")


def test_sfm_and_up_options_reach_build_and_the_poses_key(tmp_path):
    from splattwin.pipeline.build import resolved_config, stage_keys

    p = build_parser()
    o = resolve_options(p.parse_args(["build", "data", "--out", "t", "--up=-z", "--poses.max-num-features", "2000",
                                      "--no-poses.retry", "--no-poses.triangulate", "--poses.num-threads", "1",
                                      "--poses.matcher", "retrieval"]))
    assert (o.poses.up, o.poses.max_num_features, o.poses.retry, o.poses.triangulate, o.poses.num_threads,
            o.poses.matcher) == ("-z", 2000, False, False, 1, "retrieval")
    assert resolve_options(p.parse_args(["build", "data", "--out", "t", "--poses.up", "+y"])).poses.up == "+y"
    rec = resolved_config(o)["poses"]                                            # recorded in twin.json
    assert (rec["up"], rec["max_num_features"], rec["retry"], rec["num_threads"]) == ("-z", 2000, False, 1)
    base = BuildOptions.from_dict({"scene": {"width": 64, "height": 48, "views": 4, "heldout": 1},
                                   "poses": {"method": "known"}})
    k0 = stage_keys(tmp_path / "twin", base)
    for sub in ({"up": "-z"}, {"triangulate": False}, {"max_image_size": 800}, {"retry": False}):
        k = stage_keys(tmp_path / "twin", BuildOptions.from_dict({"poses": sub}, base=base))
        assert k["poses"] != k0["poses"] and k["scene"] == k0["scene"], sub
    # CPU threads do not change the result: not in the key
    assert stage_keys(tmp_path / "twin", BuildOptions.from_dict({"poses": {"num_threads": 1}}, base=base)) == k0


def test_config_file_then_flags(tmp_path):
    cfg = tmp_path / "cfg" / "twin.yaml"
    cfg.parent.mkdir()
    cfg.write_text("input: photos\n"
                   "splat: {iters: 500, depth_lambda: 0.1, lrs: {means: 0.001}}\n"
                   "semantics: {masks: masks/, fusion: {kappa: 1.2}}\n"
                   "robot: {task: default, trials: 3}\n")
    p = build_parser()
    o = resolve_options(p.parse_args(["build", "--config", str(cfg), "--out", "t", "--iters", "40"]))
    assert (o.splat.iters, o.splat.depth_lambda, o.splat.lrs.means) == (40, 0.1, 0.001)
    assert o.input == str(cfg.parent.resolve() / "photos")                    # relative to the file
    assert Path(o.semantics.masks) == cfg.parent.resolve() / "masks"
    assert (o.semantics.fusion.kappa, o.robot.trials, o.robot.task) == (1.2, 3, "default")  # "default" stays
    assert resolve_options(p.parse_args(["build", "cli_photos", "--config", str(cfg), "--out", "t"])).input == \
        "cli_photos"


def test_bad_config_file_exits_2_naming_it(tmp_path, capsys):
    cfg = tmp_path / "twin.yaml"
    cfg.write_text("splat: {iterz: 3}\n")
    assert main(["build", "x", "--out", str(tmp_path / "t"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "twin.yaml" in err and "splat.iterz" in err
    cfg.write_text("robot: {trials: lots}\n")
    assert main(["build", "x", "--out", str(tmp_path / "t"), "--config", str(cfg)]) == 2
    assert "robot.trials: expected an integer" in capsys.readouterr().err
    assert main(["build", "--out", str(tmp_path / "t")]) == 2                          # no input at all
    assert main(["build", "x", "--out", str(tmp_path / "t"), "--config", str(tmp_path / "none.yaml")]) == 2


def test_print_config_reads_back(tmp_path, capsys):
    assert main(["demo", "--print-config", "--iters", "77", "--scene.noise.p-miss", "0.5"]) == 0
    text = capsys.readouterr().out
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    p = build_parser()
    o = resolve_options(p.parse_args(["demo", "--config", str(cfg)]), demo=True)
    assert o.splat.iters == 77 and o.scene.noise.p_miss == 0.5
    assert o == resolve_options(p.parse_args(["demo", "--iters", "77", "--scene.noise.p-miss", "0.5"]), demo=True)


def test_print_config_saved_elsewhere_reads_back_the_same_paths(tmp_path, capsys, monkeypatch):
    """`build scan --masks scan/masks --print-config > configs/twin.yaml`: a config file's relative paths
    are taken from its own folder, so the printed paths must not be relative to the folder it was printed
    in (they read back as configs/scan ..., 'input does not exist'). Read back from yet another folder."""
    (tmp_path / "work" / "scan" / "masks").mkdir(parents=True)
    (tmp_path / "configs").mkdir()
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "work")
    typed = ["build", "scan", "--masks", "scan/masks", "--task", "default", "--splat.iters", "5"]
    assert main([*typed, "--print-config"]) == 0
    cfg = tmp_path / "configs" / "twin.yaml"
    cfg.write_text(capsys.readouterr().out)
    want = resolve_options(build_parser().parse_args(typed), demo=False)
    monkeypatch.chdir(tmp_path / "elsewhere")
    got = resolve_options(build_parser().parse_args(["build", "--config", str(cfg)]), demo=False)
    assert Path(got.input) == (tmp_path / "work" / "scan").resolve()
    assert Path(got.semantics.masks) == (tmp_path / "work" / "scan" / "masks").resolve()
    assert got.robot.task == "default" and got.splat.iters == 5     # a name, not a path: kept as typed
    assert got == dataclasses.replace(want, input=got.input,
                                      semantics=dataclasses.replace(want.semantics, masks=got.semantics.masks))


def test_from_dict_rejects_what_a_file_may_not_set():
    with pytest.raises(InputError, match="unknown option 'splat.progress'"):
        BuildOptions.from_dict({"splat": {"progress": False}})
    with pytest.raises(InputError, match="unknown option 'extra'"):
        BuildOptions.from_dict({"extra": {}})


def test_stage_keys_follow_their_own_sub_config(tmp_path):
    from splattwin.pipeline.build import stage_keys

    base = BuildOptions.from_dict({"scene": {"width": 64, "height": 48, "views": 4, "heldout": 1},
                                   "poses": {"method": "known"}, "robot": {"task": "default"}})
    k0 = stage_keys(tmp_path / "twin", base)

    def changed(**sub) -> set[str]:
        k = stage_keys(tmp_path / "twin", BuildOptions.from_dict(sub, base=base))
        return {s for s in k0 if k[s] != k0[s]}

    later = {"semantics", "twin", "robot", "report"}
    assert changed(splat={"depth_lambda": 0.1}) == {"splats"} | later
    assert changed(semantics={"fusion": {"kappa": 2.0}}) == later
    assert changed(geometry={"collision_faces": 900}) == {"twin", "robot", "report"}
    assert changed(robot={"trials": 2}) == {"robot", "report"}
    # what does not change results does not change keys
    assert changed(splat={"checkpoint_every": 7}, robot={"resume": False,
                                                         "cluster": {"executor": "ray", "ray_address": "auto",
                                                                     "max_retries": 0, "workers": 1}}) == set()
    quiet = dataclasses.replace(base, splat=dataclasses.replace(base.splat, progress=False))
    assert stage_keys(tmp_path / "twin", quiet) == k0 == stage_keys(tmp_path / "twin", base.with_seed(0))


def test_resolved_config_records_absolute_paths(tmp_path):
    from splattwin.pipeline.build import resolved_config

    o = BuildOptions.from_dict({"input": "rel/photos", "robot": {"task": "default"}})
    rec = resolved_config(o)
    assert rec["input"] == str(Path("rel/photos").resolve()) and rec["robot"]["task"] == "default"
    assert rec["splat"]["iters"] == 3000 and "progress" not in rec["splat"]
    assert to_dict(o, "config")["input"] == "rel/photos"


def test_robot_key_follows_the_default_arm_model(tmp_path, monkeypatch):
    """An edited Menagerie Panda (MJCF or meshes) re-runs the trials: its folder is a robot-stage input."""
    import shutil

    from splattwin.pipeline.build import stage_keys
    from splattwin.robot.assets import panda_model_path

    root = tmp_path / "menagerie"
    src = panda_model_path().parent
    shutil.copytree(src, root / src.name)
    monkeypatch.setenv("MENAGERIE_ROOT", str(root))
    base = BuildOptions.from_dict({"scene": {"width": 64, "height": 48, "views": 4, "heldout": 1},
                                   "poses": {"method": "known"}, "robot": {"task": "default"}})
    k0 = stage_keys(tmp_path / "twin", base)
    xml = panda_model_path()
    assert xml.is_relative_to(root)
    xml.write_text(xml.read_text() + "\n<!-- edited -->\n")
    k1 = stage_keys(tmp_path / "twin", base)
    assert {s for s in k0 if k1[s] != k0[s]} == {"robot", "report"}


def test_print_config_prints_a_unicode_path_readable_and_reads_it_back(tmp_path, capsys):
    """A capture folder named `cäke` was printed as "c\\xE4ke" (PyYAML's default escapes non-ASCII text): it
    read back, but nobody could read it. Now it is printed as it is on a UTF-8 stdout and still reads back the
    same, and so does a non-UTF-8 file name (a surrogate escape, which YAML can only print escaped)."""
    from splattwin.limits import load_yaml
    from splattwin.options import dump_yaml

    cake = tmp_path / "cäke"
    odd = tmp_path / os.fsdecode(b"m\xe4sks")          # Latin-1 bytes in a file name: not UTF-8
    cake.mkdir()
    odd.mkdir()
    typed = ["build", str(cake), "--masks", str(odd), "--splat.iters", "5"]
    assert main([*typed, "--print-config"]) == 0
    text = capsys.readouterr().out
    assert f"input: {cake}\n" in text and "\\x" not in text.split("semantics:")[0]
    cfg = tmp_path / "twin.yaml"
    cfg.write_bytes(text.encode("utf-8", "surrogateescape"))
    want = resolve_options(build_parser().parse_args(typed), demo=False)
    got = resolve_options(build_parser().parse_args(["build", "--config", str(cfg)]), demo=False)
    assert Path(got.input) == cake and Path(got.semantics.masks) == odd
    assert got == want
    # a stream that cannot hold the characters (an ASCII terminal) gets them escaped, which reads back the same
    data = to_dict(want, "config")
    ascii_text = dump_yaml(data, "ascii")
    assert ascii_text.isascii() and "c\\xE4ke" in ascii_text
    (tmp_path / "a.yaml").write_text(ascii_text, encoding="ascii")
    assert load_yaml(tmp_path / "a.yaml") == load_yaml(cfg) == data
