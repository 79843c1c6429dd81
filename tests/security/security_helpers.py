"""Helpers of the abuse tests (imported by the test modules; conftest.py puts this folder on sys.path):
crafted files, snapshots of folders, and the check that a CLI call was refused as bad input."""

from __future__ import annotations

import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class CliResult:
    rc: int
    out: str
    err: str


def assert_bad_input(res: CliResult, *needles: str) -> None:
    """Exit 2, one error line naming each of `needles` (file names, problems), no traceback."""
    assert res.rc == 2, (res.rc, res.err[-2000:])
    assert "Traceback" not in res.err, res.err[-2000:]
    assert "error:" in res.err
    for n in needles:
        assert n in res.err, (n, res.err[-2000:])


def png_header_bomb(path: Path, width: int = 30000, height: int = 30000) -> Path:
    """A ~60-byte PNG whose header claims width x height 8-bit grey pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def yaml_alias_bomb(levels: int = 12, width: int = 9) -> str:
    """The "billion laughs": each level lists the previous one `width` times (width**levels leaves)."""
    lines = ['a0: &a0 ["lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    lines.append(f"steps:\n  - pick: *a{levels - 1}\n    place_on: box")
    return "\n".join(lines) + "\n"


def tree_snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """{relative path: (size, mtime_ns)} of every file and folder under root (symlinks not followed)."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        out[p.relative_to(root).as_posix()] = (st.st_size if p.is_file() else 0, st.st_mtime_ns)
    return out


def no_temp_files(root: Path) -> list[str]:
    """Temporary files/folders of atomic writes (`.name.tmp<PID>-XXXXXXXX`) left under root."""
    pat = re.compile(r"^\..+\.tmp\d+-[a-z0-9_]{8}")
    return [p.relative_to(root).as_posix() for p in root.rglob("*") if pat.match(p.name)]


def write_dataset_copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def npy_header_bomb(path: Path, shape=(10**6, 10**5), dtype="<i8") -> Path:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    path.write_bytes(buf.getvalue() + b"\0" * 64)
    return path
