from __future__ import annotations

import pytest

from splattwin.errors import InputError
from splattwin.lock import LOCK_NAME, STATE_DIR, holds, output_lock


def test_a_failed_command_leaves_no_folder_it_created_and_wrote_nothing_to(tmp_path):
    out = tmp_path / "new" / "out"
    with pytest.raises(InputError):
        with output_lock(out):
            assert (out / STATE_DIR / LOCK_NAME).is_file() and holds(out)
            raise InputError("bad input", tmp_path / "capture")
    assert not out.exists() and not holds(out)
    with pytest.raises(KeyboardInterrupt):   # Ctrl-C before anything was written: same
        with output_lock(out):
            raise KeyboardInterrupt
    assert not out.exists()


def test_a_folder_that_existed_or_got_outputs_stays(tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(InputError):
        with output_lock(existing):
            raise InputError("bad input", tmp_path)
    assert existing.is_dir()
    out = tmp_path / "out"
    with pytest.raises(InputError):
        with output_lock(out):
            (out / "transforms.json").write_text("{}")
            raise InputError("bad input", tmp_path)
    assert (out / "transforms.json").is_file() and (out / STATE_DIR / LOCK_NAME).is_file()
    ok = tmp_path / "ok"
    with output_lock(ok):
        pass
    assert (ok / STATE_DIR / LOCK_NAME).is_file()   # a successful run keeps its (released) lock file
