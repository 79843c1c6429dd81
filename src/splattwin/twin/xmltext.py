"""Text inside XML comments of the exports (URDF, MJCF), which carries twin.json strings (the frame's
source, the masses' source) that may come from someone else's twin.

A comment ends at the first `--` (XML forbids `--` inside one and a trailing `-`), so replacing `--` by
`- -` once is not enough: `--->` became `- -->` and closed the comment, and what followed was read as
elements (an injected `<body>`, a `<mesh file=...>` outside the twin). Runs of dashes become one dash, a
trailing dash gets a space, and characters XML 1.0 does not allow are dropped.
"""

from __future__ import annotations

import re

_DASHES = re.compile(r"-{2,}")
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def comment_text(text: str) -> str:
    """`text` made safe to stand between `<!-- ` and ` -->`: no `--`, no trailing `-`, only XML characters."""
    s = _DASHES.sub("-", _NOT_XML.sub("", str(text)))
    return s + " " if s.endswith("-") else s
