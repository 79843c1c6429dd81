from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.robot import assets
from splattwin.robot.assets import RobotModel, TCP_OFFSET_Z, add_tcp_site_xml, panda_model_path


def test_panda_present_loads_with_tcp_site():
    path = panda_model_path()
    assert path.is_file() and path.name == "panda.xml"
    m = mujoco.MjModel.from_xml_path(str(path))
    assert m.nq == 9 and m.nu == 8
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    assert sid >= 0
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    hand = m.body("hand").id
    # the site sits TCP_OFFSET_Z along the hand's z axis
    offset = d.xmat[hand].reshape(3, 3).T @ (d.site_xpos[sid] - d.xpos[hand])
    np.testing.assert_allclose(offset, [0, 0, TCP_OFFSET_Z], atol=1e-9)


def test_local_copy_records_source_and_licence():
    root = assets.menagerie_root()
    if root is None:
        pytest.skip("Panda resolved through the menagerie download cache, not a local copy")
    src = root / assets.PANDA_NAME / assets.SOURCE_FILE
    if src.is_file():  # made by --ensure (a user MENAGERIE_ROOT need not have it)
        info = json.loads(src.read_text())
        assert "Apache-2.0" in info["licence"] and "genesis-world" in info["source"]


def test_ensure_is_idempotent_when_present(tmp_path: Path, monkeypatch):
    """A present copy is returned as is: no wheel is looked for or downloaded, nothing is rewritten."""
    root = assets.menagerie_root()
    if root is None or not (root / assets.PANDA_NAME / assets.SOURCE_FILE).is_file():
        pytest.skip("no local copy made by --ensure")

    def no_download(*a, **k):
        raise AssertionError("ensure_panda looked for the wheel although the copy is present")

    monkeypatch.setattr(assets, "_find_or_download_wheel", no_download)
    xml = root / assets.PANDA_NAME / "panda.xml"
    mtime = xml.stat().st_mtime_ns
    p = assets.ensure_panda(root, quiet=True)
    assert p == xml and xml.stat().st_mtime_ns == mtime


def test_add_tcp_site_xml_inserts_once():
    xml = '<mujoco><worldbody><body name="hand" pos="0 0 0.1">\n<geom size="0.01"/></body></worldbody></mujoco>'
    once = add_tcp_site_xml(xml)
    assert once.count('name="tcp"') == 1 and add_tcp_site_xml(once) == once
    m = mujoco.MjModel.from_xml_string(once)
    assert m.site("tcp").pos[2] == pytest.approx(TCP_OFFSET_Z)
    with pytest.raises(InputError):
        add_tcp_site_xml("<mujoco/>")


def test_panda_robot_model_names(panda: RobotModel):
    assert panda.arm_joints == [f"joint{i}" for i in range(1, 8)]
    assert panda.arm_actuators == [f"actuator{i}" for i in range(1, 8)]
    assert panda.gripper_actuator == "actuator8"
    assert (panda.gripper_open, panda.gripper_closed) == (255.0, 0.0)
    assert panda.max_opening == pytest.approx(0.08)
    assert set(panda.gripper_joints) == {"finger_joint1", "finger_joint2"}


USER_ARM = """
<mujoco>
  <worldbody>
    <body name="base" pos="0.3 0 0">
      <joint name="j1" axis="0 0 1" range="-3 3"/>
      <geom type="capsule" size="0.03" fromto="0 0 0 0 0 0.3"/>
      <body name="wrist" pos="0 0 0.3">
        <joint name="j2" axis="0 1 0" range="-2 2"/>
        <geom type="box" size="0.02 0.05 0.02"/>
        <site name="tcp" pos="0 0 0.1"/>
        <body name="fl" pos="0 0.02 0.08"><joint name="f1" type="slide" axis="0 1 0" range="0 0.03"/>
          <geom type="box" size="0.005 0.005 0.02"/></body>
        <body name="fr" pos="0 -0.02 0.08"><joint name="f2" type="slide" axis="0 -1 0" range="0 0.03"/>
          <geom type="box" size="0.005 0.005 0.02"/></body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position name="a1" joint="j1" kp="100"/>
    <position name="a2" joint="j2" kp="100"/>
    <position name="grip" joint="f1" kp="50" ctrlrange="0 0.03"/>
  </actuator>
</mujoco>
"""


def test_user_mjcf_is_described(tmp_path: Path):
    p = tmp_path / "arm.xml"
    p.write_text(USER_ARM)
    rm = RobotModel.from_mjcf(p)
    assert rm.root_body == "base" and rm.arm_joints == ["j1", "j2"] and rm.arm_actuators == ["a1", "a2"]
    assert rm.gripper_actuator == "grip" and rm.gripper_open == pytest.approx(0.03)
    assert rm.max_opening == pytest.approx(0.06)
    p.write_text(USER_ARM.replace('<site name="tcp" pos="0 0 0.1"/>', ""))
    with pytest.raises(InputError, match="tcp"):
        RobotModel.from_mjcf(p)


FAKE_PANDA = """<mujoco model="panda">
  <worldbody>
    <body name="link0"><geom size="0.05"/>
      <body name="hand" pos="0 0 0.5">
        <geom type="box" size="0.02 0.08 0.02"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _fake_wheel(wheel_dir: Path, readme: str = "## License\n\nThis model is released under an Apache-2.0 License.\n"):
    import zipfile

    wheel_dir.mkdir(parents=True, exist_ok=True)
    w = wheel_dir / f"genesis_world-{assets.GENESIS_VERSION}-py3-none-any.whl"
    with zipfile.ZipFile(w, "w") as z:
        z.writestr(assets.GENESIS_PREFIX + "panda.xml", FAKE_PANDA)
        z.writestr(assets.GENESIS_PREFIX + "README.md", readme)
        z.writestr(assets.GENESIS_PREFIX + "assets/dummy.txt", "mesh placeholder")
        z.writestr("genesis/other/big.bin", "not extracted")
        z.writestr(f"genesis_world-{assets.GENESIS_VERSION}.dist-info/licenses/LICENSE", "Apache License 2.0")
    return w


def test_ensure_extracts_only_the_panda_from_a_wheel(tmp_path: Path):
    """The provisioning path offline: a wheel laid out like genesis-world's, no network."""
    _fake_wheel(tmp_path / "wheels")
    dest = tmp_path / "menagerie"
    xml = assets.ensure_panda(dest, tmp_path / "wheels", quiet=True)
    assert xml == dest / assets.PANDA_NAME / "panda.xml"
    files = sorted(p.relative_to(dest / assets.PANDA_NAME).as_posix() for p in (dest / assets.PANDA_NAME).rglob("*") if p.is_file())
    assert files == ["LICENSE", "README.md", "SOURCE.json", "assets/dummy.txt", "panda.xml"]
    info = json.loads((dest / assets.PANDA_NAME / "SOURCE.json").read_text())
    assert f"genesis-world=={assets.GENESIS_VERSION}" in info["source"] and len(info["wheel_sha256"]) == 64
    m = mujoco.MjModel.from_xml_path(str(xml))
    assert m.site("tcp").pos[2] == pytest.approx(TCP_OFFSET_Z)
    mtime = xml.stat().st_mtime_ns
    assert assets.ensure_panda(dest, tmp_path / "wheels", quiet=True) == xml and xml.stat().st_mtime_ns == mtime
    assert not [p for p in dest.iterdir() if p.name.startswith(".panda-")]   # no staging left behind


def test_ensure_refuses_unlicensed_assets(tmp_path: Path):
    _fake_wheel(tmp_path / "wheels", readme="no licence statement here")
    with pytest.raises(InputError, match="Apache-2.0"):
        assets.ensure_panda(tmp_path / "m", tmp_path / "wheels", quiet=True)
    assert not (tmp_path / "m" / assets.PANDA_NAME).exists()


def test_menagerie_root_env_is_honoured(tmp_path: Path, monkeypatch):
    _fake_wheel(tmp_path / "wheels")
    assets.ensure_panda(tmp_path / "m", tmp_path / "wheels", quiet=True)
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path / "m"))
    assert panda_model_path() == tmp_path / "m" / assets.PANDA_NAME / "panda.xml"
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path / "empty"))
    with pytest.raises(InputError, match="--ensure"):
        panda_model_path()


def test_ensure_panda_logs_instead_of_printing(tmp_path: Path, capsys, caplog):
    """A library call printed to stdout (audit 8A, L9); the command still prints the messages."""
    import json
    import logging

    d = tmp_path / assets.PANDA_NAME
    d.mkdir()
    (d / "panda.xml").write_text("<mujoco/>")
    (d / assets.SOURCE_FILE).write_text(json.dumps({"source": "test copy"}))
    with caplog.at_level(logging.INFO, logger="splattwin.robot.assets"):
        assert assets.ensure_panda(tmp_path) == d / "panda.xml"
    assert capsys.readouterr().out == "" and "Panda assets present" in caplog.text and "test copy" in caplog.text
    assets.main(["--ensure", "--dest", str(tmp_path)])
    assert "Panda assets present" in capsys.readouterr().out
    assets.main(["--ensure", "--dest", str(tmp_path), "--quiet"])
    assert "Panda assets present" not in capsys.readouterr().out
