"""Stage options: one dataclass per stage is the only place where an option's default, type, unit and
help text are written. Command-line flags (the stage's own command and `build`/`demo`), config files
(`build --config twin.yaml`), the resolved config in twin.json and the stage keys are all derived from it.

Declaring an option (a plain dataclass field whose metadata carries the rest):

    @dataclass
    class FusionOptions:
        kappa: float = option(1.5, "consensus strictness: tau = N / kappa", build_alias="kappa")
        depth_tol: float = option(0.02, "visibility depth tolerance", unit="m")

Metadata (all optional): `help`, `unit`, `choices`; `flag` (the flag's name when it is not the field's);
`aliases` (more flag names on the stage's own command, e.g. old names); `build_alias` (a short flag on
`build`/`demo`, e.g. `--iters` for `--splat.iters`); `degrees` (the flag takes degrees, the field holds
radians); `cli=False` (set from Python or a config file only); `path=True` (a file or folder: the
pipeline hashes its content, not its name; a relative path in a config file is taken from the file's
folder); `hashed=False` (does not change the result, e.g. worker counts: left out of stage keys);
`runtime=True` (set by whoever runs the stage, e.g. progress bars: no flag on `build`, not in config files).

Why a small generator of our own and not tyro (which nerfstudio's and gsplat's trainers use): our CLI is
argparse with sub-commands that each stage registers (`splattwin/<stage>/cli.py`), with positional
arguments, old flag names kept working, and checks that raise `InputError` (exit code 2); tyro builds a
whole parser from a callable's signature and would own it. The generator below reads only
`dataclasses.fields` and their metadata, imports nothing heavy (`splattwin --help` does not import
torch), and handles the types our options use: bool, int, float, str, Path, tuples, `X | None` and
nested option dataclasses.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import types
import typing
from dataclasses import MISSING, Field, dataclass, field
from pathlib import Path
from typing import Any, Iterable

from splattwin.errors import InputError

_DEST = "@"  # argparse dest prefix of generated flags: "@splat.iters" never clashes with other arguments


def option(default: Any = MISSING, help: str = "", *, factory: Any = None, unit: str | None = None,
           choices: Iterable | None = None, flag: str | None = None, aliases: Iterable[str] = (),
           build_alias: str | None = None, degrees: bool = False, cli: bool = True, path: bool = False,
           hashed: bool = True, runtime: bool = False) -> Any:
    """A dataclass field with its option metadata (see the module docstring). `factory` for mutable or
    nested defaults (`option(factory=FusionOptions, help=...)`)."""
    meta = {"help": help, "unit": unit, "choices": tuple(choices) if choices is not None else None, "flag": flag,
            "aliases": tuple(aliases), "build_alias": build_alias, "degrees": degrees, "cli": cli, "path": path,
            "hashed": hashed and not runtime, "runtime": runtime}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


# -- field types ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spec:
    """One option field with its resolved type: `base` without `| None`, `optional` when None is allowed,
    `nested` the option dataclass when the field holds one, `item`/`length` for tuples."""

    field: Field
    base: Any
    optional: bool
    nested: type | None = None
    item: Any = None
    length: int | None = None  # tuple length; None: any length

    @property
    def name(self) -> str:
        return self.field.name

    @property
    def meta(self) -> dict:
        return dict(self.field.metadata)

    def default(self) -> Any:
        if self.field.default is not MISSING:
            return self.field.default
        if self.field.default_factory is not MISSING:
            return self.field.default_factory()
        return MISSING


_SPECS: dict[type, list[Spec]] = {}


def specs(cls: type) -> list[Spec]:
    """The option fields of dataclass `cls` with resolved types (cached)."""
    if cls not in _SPECS:
        mod = sys.modules.get(cls.__module__)
        ns = dict(vars(mod)) if mod else {}
        out = []
        for f in dataclasses.fields(cls):
            t = f.type
            if isinstance(t, str):
                try:
                    t = eval(t, ns)  # noqa: S307 - the annotation text of our own dataclass
                except Exception:  # a TYPE_CHECKING-only name: allowed for fields that are not options
                    t = None
            out.append(_spec(f, t))
        _SPECS[cls] = out
    return _SPECS[cls]


def _spec(f: Field, t: Any) -> Spec:
    optional = False
    origin = typing.get_origin(t)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(t) if a is not type(None)]
        optional = len(args) < len(typing.get_args(t))
        # `str | tuple[...]`: the first type is the form flags and config files use (text); Python
        # callers may pass the parsed form (the stage normalises it)
        t = args[0]
        origin = typing.get_origin(t)
    if dataclasses.is_dataclass(t):
        return Spec(f, t, optional, nested=t)
    if origin is tuple or t is tuple:
        args = typing.get_args(t)
        if not args:
            return Spec(f, tuple, optional, item=float, length=None)
        if len(args) == 2 and args[1] is Ellipsis:
            return Spec(f, tuple, optional, item=args[0], length=None)
        return Spec(f, tuple, optional, item=args[0], length=len(args))
    return Spec(f, t, optional)


def is_option(spec: Spec, build: bool = True) -> bool:
    """Fields that flags and config files reach: plain values of a supported type, or nested options.
    build: on `build`/`demo` and in config files, where run-time fields (progress bars, scratch folders)
    are set by the pipeline; a stage's own command has flags for those too."""
    if not spec.meta.get("cli", True) or (build and spec.meta.get("runtime")):
        return False
    return spec.nested is not None or spec.base in (bool, int, float, str, Path, tuple)


# -- command-line flags -----------------------------------------------------------------------------
def flag_name(spec: Spec) -> str:
    return (spec.meta.get("flag") or spec.name).replace("_", "-")


def flag_spellings(cls: type, name: str, stage: str) -> str:
    """Option `name` of `cls` as a message names it for both commands that take it: the stage's own command
    (its flag, then its other names) and `build`, where it is `--STAGE.FLAG` unless its short build alias
    is the same flag: '--max-num-features (or --max-features; build: --poses.max-num-features)',
    '--marker-size'. A message shared by the two commands must not send `build` users to a flag they lack."""
    spec = next(s for s in specs(cls) if s.name == name)
    own = ["--" + flag_name(spec)] + [f"--{a}" for a in spec.meta.get("aliases", ()) if a != flag_name(spec)]
    alias = spec.meta.get("build_alias")
    build = f"--{alias}" if alias else f"--{stage}.{flag_name(spec)}"
    if build in own:
        return own[0]
    return own[0] + " (" + (f"or {', '.join(own[1:])}; " if len(own) > 1 else "") + f"build: {build})"


def _fmt(v: Any, spec: Spec) -> str:
    if v is None or v == ():
        return "none"
    if spec.meta.get("degrees") and isinstance(v, (int, float)):
        v = round(math.degrees(v), 6)
    if isinstance(v, tuple):
        return " ".join(_fmt(x, spec) for x in v)
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def help_text(spec: Spec) -> str:
    m = spec.meta
    unit = "deg" if m.get("degrees") else m.get("unit")
    d = spec.default()
    text = m.get("help") or spec.name.replace("_", " ")
    if unit:
        text += f" [{unit}]"
    # an option whose None means "decided per input" says so in its help ("default 30 for a video, ...")
    said = d is None and "default" in text
    if spec.nested is None and d is not MISSING and not said:
        text += (" (default on)" if d else " (default off)") if spec.base is bool else f" (default {_fmt(d, spec)})"
    return text.replace("%", "%%")


def _converter(spec: Spec):
    base = spec.item if spec.base is tuple else spec.base
    deg = spec.meta.get("degrees")

    def conv(text: str):
        if spec.optional and spec.base is not tuple and text.strip().lower() == "none":
            return None
        v = base(text) if base in (int, float, str, Path) else text
        return math.radians(v) if deg else v
    conv.__name__ = getattr(base, "__name__", "value")  # argparse names the type in its error message
    return conv


def dest(name: str, prefix: str = "") -> str:
    """The argparse dest of option `name`'s generated flag: for an extra spelling of the same option
    (`add_argument("--sfm", dest=dest("method"), action="store_const", const="sfm", default=SUPPRESS)`)."""
    return _DEST + prefix + name


def add_command(sub: argparse._SubParsersAction, name: str, func) -> argparse.ArgumentParser:
    """Add the sub-command `name`, run as `func(args) -> exit code`. Its text is `func`'s docstring,
    written once: the first paragraph is the one-line help in `splattwin --help`, the whole docstring
    the command's description."""
    import inspect

    doc = inspect.cleandoc(func.__doc__ or "")
    summary = " ".join(doc.split("\n\n")[0].split()).rstrip(".")
    summary = summary[:1].lower() + summary[1:]  # like the other entries of `splattwin --help`
    p = sub.add_parser(name, help=summary, description=doc)
    p.set_defaults(func=func)
    return p


def add_options(parser: argparse.ArgumentParser, cls: type, prefix: str = "", *, include: Iterable[str] | None = None,
                exclude: Iterable[str] = (), build: bool = False, title: str | None = None) -> None:
    """Add a flag for every option of `cls` (nested option dataclasses recursively, as `--sub.name`).

    prefix: "" on a stage's own command; "splat." etc. on `build` (then `build_alias` flags are added too,
    and `aliases` are not). Defaults are not given to argparse (they stay in the dataclass): an absent
    flag leaves the value of the config file, or the dataclass default."""
    include = set(include) if include is not None else None
    exclude = set(exclude)
    target = parser.add_argument_group(title) if title else parser
    nested = []
    for spec in specs(cls):
        if (include is not None and spec.name not in include) or spec.name in exclude or not is_option(spec, build):
            continue
        if spec.nested is not None:
            nested.append(spec)
            continue
        m = spec.meta
        flags = [f"--{prefix}{flag_name(spec)}"]
        if build and m.get("build_alias"):
            flags.append(f"--{m['build_alias']}")
        if not build:
            flags += [f"--{a}" for a in m.get("aliases", ())]
        kw: dict[str, Any] = {"dest": _DEST + prefix + spec.name, "default": argparse.SUPPRESS, "help": help_text(spec)}
        if spec.base is bool:
            target.add_argument(*flags, action=argparse.BooleanOptionalAction, **kw)
            continue
        if spec.base is tuple:
            kw["nargs"] = spec.length or "+"
        if m.get("choices"):
            kw["choices"] = m["choices"]
        kw["type"] = _converter(spec)
        if not m.get("choices"):
            kw["metavar"] = (m.get("flag") or spec.name).upper()
        target.add_argument(*flags, **kw)
    for spec in nested:
        add_options(parser, spec.nested, f"{prefix}{spec.name}.", build=build,
                    title=f"{prefix}{spec.name}: {spec.meta.get('help') or ''}".rstrip(": ") if build else None)


def given(ns: argparse.Namespace, cls: type, prefix: str = "") -> dict[str, Any]:
    """{field: value} of the flags of `cls` given on the command line (nested options as dicts)."""
    out: dict[str, Any] = {}
    for spec in specs(cls):
        if spec.nested is not None:
            sub = given(ns, spec.nested, f"{prefix}{spec.name}.")
            if sub:
                out[spec.name] = sub
        elif hasattr(ns, _DEST + prefix + spec.name):
            v = getattr(ns, _DEST + prefix + spec.name)
            out[spec.name] = tuple(v) if spec.base is tuple and v is not None else v
    return out


def from_args(cls: type, ns: argparse.Namespace, prefix: str = "", base: Any = None, **overrides: Any) -> Any:
    """An instance of `cls`: `base` (or the defaults), then the flags given on the command line, then
    `overrides` (values the command computes itself, e.g. a work folder)."""
    return merge(base if base is not None else cls(), {**given(ns, cls, prefix), **overrides})


def merge(obj: Any, values: dict[str, Any]) -> Any:
    """Copy of option object `obj` with `values` set ({field: value}, nested option objects as dicts)."""
    cls = type(obj)
    kw = {}
    by_name = {s.name: s for s in specs(cls)}
    for k, v in values.items():
        spec = by_name[k]
        if spec.nested is not None and isinstance(v, dict):
            cur = getattr(obj, k)
            kw[k] = merge(cur if cur is not None else spec.nested(), v)
        else:
            kw[k] = v
    return dataclasses.replace(obj, **kw)


def set_everywhere(obj: Any, name: str, value: Any) -> Any:
    """Copy of `obj` with field `name` set to `value` in it and in every nested option object that has it
    (`--seed` on build sets every stage's seed; a build without progress bars turns off every stage's)."""
    kw = {}
    for spec in specs(type(obj)):
        cur = getattr(obj, spec.name)
        if spec.name == name:
            kw[name] = value
        elif spec.nested is not None and cur is not None:
            kw[spec.name] = set_everywhere(cur, name, value)
    return dataclasses.replace(obj, **kw)


# powers of a length a unit carries: a value in this unit is multiplied by factor ** power
LENGTH_POWERS = {"m": 1, "kg/m^3": -3}


def scale_lengths(obj: Any, factor: float) -> Any:
    """Copy of option object `obj` with every length option (unit "m", and densities "kg/m^3" by
    factor^-3) expressed in a frame where one metre is `factor` units, nested options included; None
    stays None (derived later from the scaled values). factor 1 returns `obj` itself, unchanged.

    An unscaled twin's stages run with their options passed through this, `factor` being the frame's
    nominal metre (`splattwin.poses.twin_frame.TwinFrame.length_scale`): the thresholds written in
    metres become the same share of the scene as in a metric capture."""
    if factor == 1.0:
        return obj
    kw = {}
    for spec in specs(type(obj)):
        cur = getattr(obj, spec.name)
        power = LENGTH_POWERS.get(spec.meta.get("unit"))
        if spec.nested is not None and cur is not None:
            kw[spec.name] = scale_lengths(cur, factor)
        elif power is not None and cur is not None and not isinstance(cur, bool):
            f = float(factor) ** power
            kw[spec.name] = (tuple(float(v) * f for v in cur) if isinstance(cur, (tuple, list))
                             else float(cur) * f)
    return dataclasses.replace(obj, **kw)


# -- dicts and config files -------------------------------------------------------------------------
def to_dict(obj: Any, mode: str = "record") -> dict[str, Any]:
    """Plain nested dict of option object `obj` (tuples as lists, paths as strings), for JSON/YAML.

    mode "record": every option but the run-time ones (the resolved config in twin.json); "config": only
    what a config file may set (`--print-config`, read back by `from_dict`); "key": only what changes a
    stage's result (no path, unhashed or run-time fields: the stage keys)."""
    out: dict[str, Any] = {}
    for spec in specs(type(obj)):
        m = spec.meta
        if m.get("runtime") or (mode == "config" and not is_option(spec)):
            continue
        if mode == "key" and (not m.get("hashed", True) or m.get("path")):
            continue
        v = getattr(obj, spec.name)
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            v = to_dict(v, mode) if spec.nested is not None else dataclasses.asdict(v)
        out[spec.name] = _plain(v)
    return out


def absolute_paths(obj: Any) -> Any:
    """`obj` (an option object) with its path options (`path=True`) made absolute, from the current
    folder: what twin.json records, and what `--print-config` prints so that the file reads back the same
    wherever it is saved (a config file's relative paths are taken from its own folder). "default" and
    empty values are names, not paths: kept."""
    kw = {}
    for spec in specs(type(obj)):
        v = getattr(obj, spec.name)
        if spec.nested is not None and v is not None:
            kw[spec.name] = absolute_paths(v)
        elif spec.meta.get("path") and v not in (None, "", "default"):
            kw[spec.name] = type(v)(Path(v).resolve()) if isinstance(v, Path) else str(Path(v).resolve())
    return dataclasses.replace(obj, **kw)


def _plain(v: Any) -> Any:
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, Path):
        return str(v)
    return v


def from_dict(cls: type, data: Any, where: str | Path | None = None, base: Any = None, *, root: Path | None = None,
              _at: str = "") -> Any:
    """An instance of `cls` from a plain nested dict (a config file), on top of `base` (or the defaults).

    Every key must name an option and every value must have the option's type: anything else is an
    InputError naming `where` and the option. Relative paths are taken from `root` (the file's folder)."""
    if not isinstance(data, dict):
        raise InputError(f"options{' ' + _at.rstrip('.') if _at else ''} must be a mapping of option names to values, "
                         f"got {type(data).__name__}", where)
    by_name = {s.name: s for s in specs(cls) if is_option(s)}
    values: dict[str, Any] = {}
    for k, v in data.items():
        key = str(k).replace("-", "_")
        spec = by_name.get(key)
        if spec is None:
            known = ", ".join(sorted(by_name))
            raise InputError(f"unknown option '{_at}{k}' (options here: {known})", where)
        if spec.nested is not None:
            if v is None and spec.optional:
                values[key] = None
                continue
            cur = getattr(base, key, None) if base is not None else None
            values[key] = from_dict(spec.nested, v, where, cur, root=root, _at=f"{_at}{key}.")
        else:
            values[key] = _check(spec, v, where, f"{_at}{key}", root)
    obj = base if base is not None else cls()
    return dataclasses.replace(obj, **values)


def _check(spec: Spec, v: Any, where, name: str, root: Path | None) -> Any:
    def bad(expected: str):
        return InputError(f"option {name}: expected {expected}, got {v!r}", where)

    if v is None:
        if spec.optional:
            return None
        raise bad("a value (it cannot be null)")
    b = spec.base
    if b is bool:
        if not isinstance(v, bool):
            raise bad("true or false")
    elif b is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise bad("an integer")
    elif b is float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise bad("a finite number")
        v = float(v)
    elif b in (str, Path):
        if not isinstance(v, (str, int, float)) or isinstance(v, bool):
            raise bad("a string")
        v = str(v)
        if spec.meta.get("path") and root is not None and v and not Path(v).is_absolute() and v != "default":
            v = str(root / v)
        if b is Path:
            v = Path(v)
    elif b is tuple:
        if not isinstance(v, (list, tuple)) or (spec.length is not None and len(v) != spec.length):
            raise bad(f"a list of {spec.length or 'some'} values")
        item = Spec(spec.field, spec.item, False)
        v = tuple(_check(item, x, where, name, root) for x in v)
    choices = spec.meta.get("choices")
    if choices and v not in choices:
        raise InputError(f"option {name}: {v!r} is not one of {', '.join(map(str, choices))}", where)
    return v


def load_config(path: str | Path, cls: type, base: Any = None) -> Any:
    """Options of type `cls` from a YAML (or JSON) config file, read with the bounded loader of
    `splattwin.limits`; relative paths inside are taken from the file's folder."""
    from splattwin.limits import load_yaml

    path = Path(path)
    data = load_yaml(path)
    if data is None:
        data = {}
    return from_dict(cls, data, path, base, root=path.resolve().parent)


def add_config_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, metavar="FILE.yaml",
                        help="options from a YAML file (nested like the flags: splat: {iters: 3000}); "
                             "flags given on the command line override it")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved options as YAML (a starting point for --config) and exit")


def add_progress_flag(parser: argparse.ArgumentParser) -> None:
    """`--no-progress`: a run-time choice, not an option of any stage (no stage key changes with it)."""
    parser.add_argument("--no-progress", dest="progress", action="store_false",
                        help="no progress bars (terminal) or progress lines (log)")


def dump_yaml(data: dict, encoding: str | None = "utf-8") -> str:
    """`data` as YAML that `load_yaml` reads back identically. Non-ASCII text (a path `c\u00e4ke/`) is written
    as it is, readable, where `encoding` (the stream's, e.g. sys.stdout's) can hold it: PyYAML's default
    escaped it ("c\\xE4ke"). Otherwise (an ASCII terminal) it stays escaped, which reads back the same.
    Characters YAML cannot print (a non-UTF-8 file name's surrogate escapes) are escaped either way."""
    import codecs

    import yaml

    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=False, allow_unicode=True)
    try:
        text.encode(codecs.lookup(encoding or "ascii").name)
    except (LookupError, UnicodeEncodeError):
        return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
    return text


def print_yaml(data: dict) -> None:
    """`--print-config`: `data` as YAML on stdout, readable in its encoding (`dump_yaml`)."""
    import sys

    print(dump_yaml(data, getattr(sys.stdout, "encoding", None)), end="")
