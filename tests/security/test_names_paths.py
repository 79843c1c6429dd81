"""Validated names and confined paths (`splattwin.names`, `splattwin.paths`), fuzzed with hypothesis:
whatever text arrives, a name is never a path and a path read from a file never leaves its folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from splattwin.errors import InputError
from splattwin.names import check_unique, name_from_label, object_name, view_name
from splattwin.paths import child, confined, is_inside

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# Text biased towards the characters that make paths: separators, dots, NUL, spaces, unicode.
nasty = st.lists(st.sampled_from(list("ab./\\\x00 ~-_:*\n\t") + ["..", "é", "😀", "CON", "/etc"]),
                 max_size=20).map("".join)
any_text = st.one_of(nasty, st.text(max_size=80))


@SETTINGS
@given(text=any_text)
def test_an_object_name_is_never_a_path(tmp_path, text):
    try:
        name = object_name(text)
    except InputError as e:
        assert "not allowed" in str(e) or "reserved" in str(e)
        return
    assert name == text and 1 <= len(name) <= 64
    assert "/" not in name and "\\" not in name and "\x00" not in name and name not in (".", "..")
    assert not name.startswith((".", " ", "-")) and not name.endswith((".", " "))
    p = child(tmp_path, name)
    assert p.parent == tmp_path and is_inside(p, tmp_path)


@SETTINGS
@given(text=any_text)
def test_a_view_name_is_one_path_component(tmp_path, text):
    try:
        name = view_name(text)
    except InputError:
        return
    assert name not in ("", ".", "..") and "/" not in name and "\x00" not in name
    assert (tmp_path / name).parent == tmp_path


@SETTINGS
@given(rel=any_text)
def test_confined_paths_stay_inside(tmp_path, rel):
    root = tmp_path / "root"
    root.mkdir(exist_ok=True)
    try:
        p = confined(root, rel, where=root / "file.json")
    except InputError as e:
        assert "file.json" in str(e)  # the file the path came from is named
        return
    assert is_inside(p, root)
    assert not Path(rel).is_absolute()


@pytest.mark.parametrize("rel", ["../x", "a/../../x", "/etc/passwd", "~/x", "", "a\x00b", "./../x", "a/b/../../../x"])
def test_known_escapes_are_refused(tmp_path, rel):
    with pytest.raises(InputError):
        confined(tmp_path, rel, tmp_path / "t.json")


def test_symbolic_links_out_of_the_folder_are_refused(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    (outside / "secret.png").write_bytes(b"x")
    os.symlink(outside, root / "link")
    with pytest.raises(InputError, match="leads outside"):
        confined(root, "link/secret.png", root / "t.json")
    os.symlink(root / "inner_target", root / "inner_link")  # a link that stays inside is fine
    assert confined(root, "inner_link/x", root / "t.json") == root / "inner_link" / "x"


@pytest.mark.parametrize("bad", ["../../victim", "/etc", "a/b", ".", "..", ".hidden", "x" * 65, "NUL", "a\tb",
                                 "", " lead", "trail.", 7, None])
def test_object_names_refused(bad):
    with pytest.raises(InputError):
        object_name(bad, "cats.json")


def test_labels_become_names_and_duplicates_are_refused():
    assert name_from_label("  toy \t hammer\n") == "toy hammer"
    assert object_name("blue_box") == "blue_box"
    with pytest.raises(InputError, match="'Box' and 'box' both give export IDs 'Box' and 'box', the same ignoring case"):
        check_unique(["Box", "box"], "c.json")
    with pytest.raises(InputError, match="'toy hammer' and 'toy_hammer' both give export ID 'toy_hammer'"):
        check_unique(["toy hammer", "toy_hammer"], "c.json")  # one MoveIt id, one file name
    with pytest.raises(InputError, match="object names 'a-b' and 'a_b' both give export ID 'a_b'"):
        check_unique(["a-b", "a_b"], "c.json")
    with pytest.raises(InputError, match="object name 'mug' appears twice"):
        check_unique(["mug", "mug"], "c.json")
    check_unique(["a", "b", "a b"])


def test_name_refusals_say_what_to_do():
    # 'é' is a letter, just not an ASCII one (audit 6b D12)
    with pytest.raises(InputError, match=r"ASCII letters.*'é' is not ASCII: write e\.g\. 'e' for 'é'"):
        object_name("mug. café", "tasse café.png")
    with pytest.raises(InputError, match="ASCII letters") as e:
        object_name("a/b", "x.json")
    assert "not ASCII" not in str(e.value)
    # a reserved --prompt phrase: the phrase is the name, so the hint is a longer phrase, not a rename
    with pytest.raises(InputError, match="the prompt phrase is the object's name.*'dining table'"):
        object_name("table", "--prompt", "object name from the prompt phrase")
    with pytest.raises(InputError, match=r"rename the object \(e\.g\. 'Table 1'\)"):
        object_name("Table", "scene.json")
