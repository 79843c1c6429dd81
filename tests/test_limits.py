"""splattwin.limits: bounded readers give an InputError naming the file."""

from __future__ import annotations

import pytest

from splattwin.errors import InputError


def test_yaml_long_integer_names_the_file(tmp_path):
    """Python refuses integers of more than 4300 digits with a ValueError that load_yaml let through
    (a task YAML gave an internal error, exit 1)."""
    from splattwin.limits import load_yaml

    p = tmp_path / "task.yaml"
    p.write_text("n: " + "7" * 5000 + "\n")
    with pytest.raises(InputError, match="number too long to read") as e:
        load_yaml(p)
    assert e.value.path == p and len(str(e.value)) < 300
