"""Validated names: object / label names and view names that come from files or the command line.

Object names become folder and file names (`objects/<name>/`, `export/<name>.urdf`,
`masks/<view>/<name>.png`), MuJoCo body names, URDF link names and MoveIt ids, and they come from
files other people made (COCO categories, polygon JSON, mask folders, twin.json, scene.json) or from
`--object`. Every entry point checks them here, so a name can never be a path: `../../victim`, `/etc`,
`a/b`, `.` and `..` are refused with an InputError naming the file.

object names: 1-64 ASCII letters, digits, `_`, `-`, `.` and single inner spaces ("toy hammer" is a
    common COCO category), starting with a letter or digit and not ending with `.` or a space (Windows
    drops those), and not a Windows device name (CON, NUL, COM1...). `name_from_label` first collapses
    runs of whitespace (tabs, newlines, leading/trailing) into single spaces, then checks. Uniqueness
    is by export ID ignoring case (` `, `-`, `.` and `_` alike), so no two objects collide as files on
    a case-insensitive file system or as IDs in an export.
reserved object names: the fixed names the exports give the twin's own parts (`RESERVED_NAMES`:
    `world`, `table`, `floor`, `background`, `background_obstacles`, `twin`, `twin_z_up`), compared
    by export ID ignoring case (`Table`, `twin-z-up` too). An object so named would clash with them
    (two URDF links `table`, MoveIt's table box replaced, a lost glTF node, MuJoCo's "repeated name
    'world'"), and a robot task's `place_on: table` would be ambiguous: refused at the input, never
    renamed behind the user's back.
export IDs (`export_id`): the name as every export writes it (URDF links and mesh files' link names,
    MJCF bodies, MoveIt ids, glTF nodes): each character outside [A-Za-z0-9_] becomes `_`, and `obj_`
    goes in front of a leading digit ("toy hammer" -> `toy_hammer`, "3.5 in pipe" -> `obj_3_5_in_pipe`).
    It depends on the name alone (stable across builds), and `check_unique` compares names by it, so
    it is unique within a twin. twin.json keeps the human name and records the ID per object.
view names (image stems of real photos: `IMG 0001 (2)`): any single path component of at most 255
    bytes without `/`, `\\`, NUL or other control characters, and not `.` or `..`.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from splattwin.errors import InputError, short_repr

MAX_NAME_LEN = 64
MAX_COMPONENT_BYTES = 255
_NAME_RE = re.compile(r"[A-Za-z0-9](?:(?:[A-Za-z0-9_.\-]| (?! )){0,62}[A-Za-z0-9_\-])?")
_WINDOWS_DEVICES = {"con", "prn", "aux", "nul", *(f"com{i}" for i in range(1, 10)), *(f"lpt{i}" for i in range(1, 10))}
_CONTROL_RE = re.compile(r"[\x00-\x1f\x7f]")


def object_name(text, where: str | Path | None = None, what: str = "object name") -> str:
    """`text` if it is a valid object name (see module docstring), else InputError naming `where`."""
    if not isinstance(text, str):
        raise InputError(f"{what} must be a string, got {type(text).__name__} {short_repr(text, 80)}", where)
    if not _NAME_RE.fullmatch(text):
        foreign = sorted({c for c in text if not c.isascii() and c.isprintable()})
        why = ""
        if foreign:   # a letter such as 'é' is a letter, just not an ASCII one: say which
            import unicodedata

            plain = unicodedata.normalize("NFKD", foreign[0]).encode("ascii", "ignore").decode()
            why = (f" ({', '.join(repr(c) for c in foreign[:5])} {'is' if len(foreign) == 1 else 'are'} not ASCII"
                   + (f": write e.g. {plain!r} for {foreign[0]!r})" if plain else ")"))
        raise InputError(f"{what} {short_repr(text, 80)} is not allowed: use 1-{MAX_NAME_LEN} ASCII letters (A-Z, a-z), "
                         f"digits, '_', '-', '.' or single spaces, starting with a letter or digit (a name must never "
                         f"be a path){why}", where)
    if text.split(".")[0].lower() in _WINDOWS_DEVICES:
        raise InputError(f"{what} {short_repr(text, 80)} is a reserved device name on Windows", where)
    if export_id(text).lower() in RESERVED_NAMES:
        # a --prompt phrase is the object's name too (and what the detector looks for): a longer phrase
        # keeps the detection and frees the name; renaming the object alone is not possible there
        hint = ("the prompt phrase is the object's name: use a more specific phrase for it (e.g. 'dining table' "
                "or 'tabletop box')" if "prompt" in f"{what} {where}" else f"rename the object (e.g. {text + ' 1'!r})")
        raise InputError(f"{what} {short_repr(text, 80)} is reserved: the exports use "
                         f"{', '.join(sorted(RESERVED_NAMES))} for the twin's own frame, table and background; "
                         f"{hint}", where)
    return text


# fixed names of the exports (URDF links, MJCF bodies/geoms/meshes, MoveIt ids and frame, glTF nodes):
# an object may not take them (module docstring). Lower case; compared with export_id(name).lower().
RESERVED_NAMES = frozenset({"world", "table", "floor", "background", "background_obstacles", "twin", "twin_z_up"})
_ID_BAD = re.compile(r"[^A-Za-z0-9_]")


def export_id(name: str) -> str:
    """The ID every export gives object `name` (module docstring): [A-Za-z0-9_], not starting with a digit."""
    s = _ID_BAD.sub("_", name)
    return f"obj_{s}" if s[:1].isdigit() else s


def name_from_label(text, where: str | Path | None = None, what: str = "object name") -> str:
    """A human label ("toy  hammer\n") as an object name ("toy hammer"): whitespace runs become one
    space, then `object_name` checks the result (anything else not allowed is refused, not rewritten)."""
    if not isinstance(text, str):
        raise InputError(f"{what} must be a string, got {type(text).__name__} {short_repr(text, 80)}", where)
    return object_name(" ".join(text.split()), where, what)


def view_name(text, where: str | Path | None = None, what: str = "view name") -> str:
    """`text` if it is a single safe path component (see module docstring), else InputError."""
    if not isinstance(text, str):
        raise InputError(f"{what} must be a string, got {type(text).__name__} {short_repr(text, 80)}", where)
    if (not text or text in (".", "..") or "/" in text or "\\" in text or _CONTROL_RE.search(text)
            or len(text.encode("utf-8", "surrogateescape")) > MAX_COMPONENT_BYTES):
        raise InputError(f"{what} {short_repr(text, 80)} is not allowed: it must be one file name (no '/', '\\', "
                         f"control characters, '.' or '..'; at most {MAX_COMPONENT_BYTES} bytes)", where)
    return text


def check_unique(names: Iterable[str], where: str | Path | None = None, what: str = "object name") -> None:
    """InputError if a name repeats (compared by export ID ignoring case: names must not collide as files
    on case-insensitive file systems or as export IDs, where ' ', '-', '.' all become '_')."""
    seen: dict[str, str] = {}
    for n in names:
        k = export_id(n).lower()
        if k in seen:
            if seen[k] == n:
                raise InputError(f"{what} {n!r} appears twice; names must be unique", where)
            ids = (f"export ID {export_id(n)!r}" if export_id(n) == export_id(seen[k]) else
                   f"export IDs {export_id(seen[k])!r} and {export_id(n)!r}, the same ignoring case")
            raise InputError(f"{what + 's' if what.endswith('name') else what} {seen[k]!r} and {n!r} both give {ids} (names are compared by export ID "
                             f"ignoring case: ' ', '-', '.' and '_' alike); names must be unique", where)
        seen[k] = n
