"""`splattwin.errors.require_type`: the TypeError library entry points give for an argument of the wrong type
(audit 10A L19: a path or an array where an object is taken failed deep inside with an AttributeError)."""

from __future__ import annotations

from pathlib import Path

import pytest

from splattwin.errors import require_type


def test_require_type_names_the_argument_the_types_and_what_it_got():
    require_type(Path("a"), Path, "where")
    require_type(3, (str, int), "count")
    with pytest.raises(TypeError, match=r'^scene must be a Path \(Path\("x"\)\), got str$'):
        require_type("x", Path, "scene", '(Path("x"))')
    with pytest.raises(TypeError, match=r"^n must be a str or int, got float$"):
        require_type(1.5, (str, int), "n")
