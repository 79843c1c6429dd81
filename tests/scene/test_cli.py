from __future__ import annotations

import json

import pytest

from splattwin.cli import main


def test_cli_generate_writes_the_layout(tmp_path, capsys):
    out = tmp_path / "scene"
    rc = main(["scene", "generate", str(out), "--width", "48", "--height", "40", "--views", "3", "--heldout", "1",
               "--seed", "2", "--marker", "--supersample", "3", "--no-progress"])
    assert rc == 0
    assert str(out.resolve()) in capsys.readouterr().out
    tj = json.loads((out / "transforms.json").read_text())
    assert len(tj["frames"]) == 4 and tj["w"] == 48 and tj["h"] == 40
    scene = json.loads((out / "scene.json").read_text())
    assert scene["seed"] == 2 and scene["marker"]["id"] == 0 and scene["options"]["supersample"] == 3
    for f in tj["frames"]:
        assert (out / f["file_path"]).is_file() and (out / f["depth_file_path"]).is_file()
        assert (out / f["label_path"]).is_file() and "mask_path" not in f  # not a nerfstudio loss mask
    assert len(list((out / "masks" / "noisy").iterdir())) == 4
    assert len(list((out / "meshes").glob("*.ply"))) == 6


@pytest.mark.parametrize("args", [["--views", "0"], ["--width", "-3"], ["--heldout", "-1"],
                                  ["--marker-size", "0"], ["--supersample", "0"], ["--supersample", "9"]])
def test_cli_bad_options_exit_2(tmp_path, capsys, args):
    rc = main(["scene", "generate", str(tmp_path / "x"), "--no-progress", *args])
    assert rc == 2
    assert "error:" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["scene", "--help"], ["scene", "generate", "--help"]])
def test_cli_help(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    assert "usage" in capsys.readouterr().out
