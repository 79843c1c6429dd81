"""Robot assets: the Franka Emika Panda with its hand from MuJoCo Menagerie, or a user MJCF.

Where the model comes from, in order:
1. `MENAGERIE_ROOT=<dir>` (the `mujoco-menagerie` package's own offline switch): `<dir>/franka_emika_panda`.
2. The local copy made by `python -m splattwin.robot.assets --ensure` (third_party/menagerie in a source
   checkout, else ~/.cache/splattwin/menagerie), used through the same `mujoco_menagerie` API.
3. `mujoco_menagerie`'s own download cache (needs GitHub access).

`--ensure` provides the local copy offline-friendly from PyPI: the `genesis-world` wheel ships the Menagerie
Panda (Apache-2.0, see its README) under genesis/assets/xml/franka_emika_panda/. Only that folder is
extracted, and a TCP site (`tcp`, between the fingertip pads, 0.1034 m along the hand's z axis) is added,
because that Menagerie revision has none.

`RobotModel` describes any arm+gripper MJCF with a TCP site: arm joints are the joints on the kinematic
chain from the root to the TCP's body, gripper joints those below it; the gripper actuator is the one not
driving an arm joint.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.hashing import sha256_file

log = logging.getLogger(__name__)

PANDA_NAME = "franka_emika_panda"
PANDA_ENTRY = "panda"
TCP_SITE = "tcp"
TCP_OFFSET_Z = 0.1034          # m, hand frame -> midpoint of the fingertip pads
GENESIS_PACKAGE = "genesis-world"
GENESIS_VERSION = "1.4.5"      # pinned: the extracted files are what the tests were run against
GENESIS_PREFIX = "genesis/assets/xml/franka_emika_panda/"
SOURCE_FILE = "SOURCE.json"
PANDA_HOME = np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])   # rad, Menagerie "home" key


def _repo_root() -> Path | None:
    """The source checkout this package runs from (editable install), else None."""
    root = Path(__file__).resolve().parents[3]
    return root if (root / "pyproject.toml").is_file() and (root / "src" / "splattwin").is_dir() else None


def default_asset_root() -> Path:
    """Folder holding `<robot name>/` copies made by `ensure_panda` (a MENAGERIE_ROOT-style tree)."""
    env = os.environ.get("SPLATTWIN_ASSETS")
    if env:
        return Path(env)
    repo = _repo_root()
    if repo is not None:
        return repo / "third_party" / "menagerie"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "splattwin" / "menagerie"


def _wheel_dir() -> Path:
    repo = _repo_root()
    base = repo / ".cache" if repo is not None else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "splattwin"
    return base / "wheels"


def menagerie_root() -> Path | None:
    """MENAGERIE_ROOT if set, else the local copy if present, else None (= menagerie download cache)."""
    env = os.environ.get("MENAGERIE_ROOT")
    if env:
        return Path(env)
    local = default_asset_root()
    if (local / PANDA_NAME / "panda.xml").is_file():
        return local
    return None


def panda_model_path(entry: str = PANDA_ENTRY) -> Path:
    """Path of the Panda (with hand) MJCF, resolved through the `mujoco_menagerie` API.

    Raises InputError with the fix when no copy is available offline.
    """
    import mujoco_menagerie

    root = menagerie_root()
    cache = mujoco_menagerie.Cache(root=root) if root is not None else mujoco_menagerie.Cache()
    robot = mujoco_menagerie.get(PANDA_NAME)
    try:
        path = robot.xml(entry, cache)
    except mujoco_menagerie.MenagerieError as e:
        raise InputError(f"Franka Panda model not available ({e}); run `python -m splattwin.robot.assets --ensure` "
                         "or set MENAGERIE_ROOT to a Menagerie checkout", root) from e
    if not path.is_file():
        raise InputError(f"no {entry} entry point in the Menagerie copy; run `python -m splattwin.robot.assets --ensure`", path)
    return path


# -- provisioning from PyPI ---------------------------------------------------------------------------

def _find_or_download_wheel(wheel_dir: Path, quiet: bool) -> Path:
    pattern = f"genesis_world-{GENESIS_VERSION}-*.whl"
    found = sorted(wheel_dir.glob(pattern))
    if found:
        return found[0]
    wheel_dir.mkdir(parents=True, exist_ok=True)
    if not quiet:
        log.info("downloading %s==%s (no dependencies) into %s ...", GENESIS_PACKAGE, GENESIS_VERSION, wheel_dir)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "-q",
           f"{GENESIS_PACKAGE}=={GENESIS_VERSION}", "-d", str(wheel_dir)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    found = sorted(wheel_dir.glob(pattern))
    if r.returncode != 0 or not found:
        raise InputError(f"could not download {GENESIS_PACKAGE}=={GENESIS_VERSION} from PyPI: {r.stderr.strip()[-500:]}", wheel_dir)
    return found[0]


def add_tcp_site_xml(xml: str) -> str:
    """Insert the `tcp` site into the `hand` body of a Menagerie panda.xml (no-op when present)."""
    if re.search(r'<site[^>]*name="tcp"', xml):
        return xml
    m = re.search(r'<body name="hand"[^>]*>\n?', xml)
    if m is None:
        raise InputError("panda.xml has no body named 'hand'")
    site = (f'                      <site name="{TCP_SITE}" pos="0 0 {TCP_OFFSET_Z}" size="0.004" '
            'rgba="1 0 0 0.6" group="4"/>\n')
    return xml[:m.end()] + site + xml[m.end():]


def ensure_panda(dest_root: Path | None = None, wheel_dir: Path | None = None, quiet: bool = False) -> Path:
    """Provide `<dest_root>/franka_emika_panda/` (with TCP site); idempotent and fast when present.

    Returns the panda.xml path. The copy is assembled in a temporary folder and renamed into place, so a
    killed run leaves either no copy or a complete one.
    """
    dest_root = Path(dest_root) if dest_root is not None else default_asset_root()
    dest = dest_root / PANDA_NAME
    if (dest / "panda.xml").is_file() and (dest / SOURCE_FILE).is_file():
        if not quiet:
            src = json.loads((dest / SOURCE_FILE).read_text())
            log.info("Panda assets present: %s (source: %s)", dest, src.get("source"))
        return dest / "panda.xml"
    wheel = _find_or_download_wheel(Path(wheel_dir) if wheel_dir else _wheel_dir(), quiet)
    dest_root.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".panda-", dir=dest_root))
    try:
        with zipfile.ZipFile(wheel) as z:
            members = [n for n in z.namelist() if n.startswith(GENESIS_PREFIX) and not n.endswith("/")]
            if not any(n.endswith("/panda.xml") for n in members):
                raise InputError(f"{wheel.name} does not contain {GENESIS_PREFIX}panda.xml", wheel)
            for n in members:
                out = stage / n[len(GENESIS_PREFIX):]
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_bytes(z.read(n))
            licence = next((n for n in z.namelist() if n.endswith(".dist-info/licenses/LICENSE")), None)
            if licence:
                (stage / "LICENSE").write_bytes(z.read(licence))
        readme = (stage / "README.md").read_text() if (stage / "README.md").is_file() else ""
        if "Apache-2.0" not in readme:
            raise InputError("the Panda README in the wheel no longer states the Apache-2.0 licence; check it by hand", wheel)
        panda_xml = stage / "panda.xml"
        panda_xml.write_text(add_tcp_site_xml(panda_xml.read_text()))
        source = {
            "source": f"PyPI {GENESIS_PACKAGE}=={GENESIS_VERSION} ({wheel.name}), folder {GENESIS_PREFIX}",
            "origin": "MuJoCo Menagerie franka_emika_panda (github.com/google-deepmind/mujoco_menagerie)",
            "licence": "Apache-2.0 (model: README.md 'License'; wheel: LICENSE)",
            "wheel_sha256": sha256_file(wheel),
            "modifications": f"added site '{TCP_SITE}' on body 'hand' at z = {TCP_OFFSET_Z} m",
        }
        (stage / SOURCE_FILE).write_text(json.dumps(source, indent=2) + "\n")
        import mujoco  # verify before publishing

        m = mujoco.MjModel.from_xml_path(str(panda_xml))
        if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, TCP_SITE) < 0:
            raise RuntimeError("TCP site missing after edit")
        if dest.exists():  # an incomplete copy (no SOURCE.json) from an older or killed run
            shutil.rmtree(dest)
        os.replace(stage, dest)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    if not quiet:
        log.info("Panda assets installed: %s\n  source: %s\n  licence: %s", dest, source["source"], source["licence"])
    return dest / "panda.xml"


# -- robot description --------------------------------------------------------------------------------

@dataclass
class RobotModel:
    """An arm + parallel gripper MJCF and the names the robot stage needs.

    xml_path: the MJCF. root_body: top body of the arm (its pose is the robot base). tcp_site: tool centre
    point between the fingertips, z = approach direction, y = finger closing axis. arm_joints /
    arm_actuators: position servos, same order. gripper_actuator: ctrl gripper_open opens, gripper_closed
    closes. max_opening: full finger gap (m). home: arm joint angles (rad) for a neutral pose (a user
    MJCF's keyframe named "home", else the middle of the joint ranges).
    vel_limits / acc_limits: per arm joint (rad/s, rad/s^2) for time parameterisation.
    """

    xml_path: Path
    root_body: str
    tcp_site: str
    arm_joints: list[str]
    arm_actuators: list[str]
    gripper_joints: list[str]
    gripper_actuator: str
    gripper_open: float
    gripper_closed: float
    max_opening: float
    home: np.ndarray
    vel_limits: np.ndarray
    acc_limits: np.ndarray
    hand_bodies: list[str] = field(default_factory=list)   # TCP body and everything below (fingers)

    @classmethod
    def panda(cls) -> "RobotModel":
        """The Menagerie Panda with hand (Franka datasheet joint velocity/acceleration limits)."""
        rm = cls.from_mjcf(panda_model_path())
        rm.home = PANDA_HOME.copy()
        rm.vel_limits = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
        rm.acc_limits = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])
        rm.max_opening = 0.08
        return rm

    @classmethod
    def from_mjcf(cls, path: str | Path, tcp_site: str = TCP_SITE) -> "RobotModel":
        import mujoco

        path = Path(path)
        if not path.is_file():
            raise InputError("robot MJCF not found", path)
        try:
            spec = mujoco.MjSpec.from_file(str(path))
            ensure_tcp_site(spec)
            spec.compiler.discardvisual = True   # names only: visual meshes cost ~1 s to compile
            model = spec.compile()
        except ValueError as e:
            raise InputError(f"robot MJCF does not compile: {e}", path) from e
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, tcp_site)
        if sid < 0:
            raise InputError(f"robot MJCF has no site named {tcp_site!r} (the tool centre point)", path)
        name = lambda t, i: mujoco.mj_id2name(model, t, i)  # noqa: E731
        tcp_body = int(model.site_bodyid[sid])
        chain = []
        b = tcp_body
        while b != 0:
            chain.append(b)
            b = int(model.body_parentid[b])
        root = chain[-1]
        hinge_slide = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        arm_j = sorted(j for j in range(model.njnt) if int(model.jnt_bodyid[j]) in chain
                       and int(model.jnt_type[j]) in hinge_slide)
        below = [bb for bb in range(model.nbody) if _is_descendant(model, bb, tcp_body)]
        grip_j = [j for j in range(model.njnt) if model.jnt_bodyid[j] in below and model.jnt_bodyid[j] != tcp_body]
        arm_act, grip_act = {}, []
        for a in range(model.nu):
            if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT) and int(model.actuator_trnid[a, 0]) in arm_j:
                arm_act[int(model.actuator_trnid[a, 0])] = a
            else:
                grip_act.append(a)
        if len(arm_act) != len(arm_j) or not grip_act:
            raise InputError("robot MJCF needs one position actuator per arm joint and one gripper actuator", path)
        g = grip_act[0]
        lo, hi = model.actuator_ctrlrange[g]
        opening = sum(float(model.jnt_range[j, 1]) for j in grip_j
                      if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE)) or 0.08
        rng = model.jnt_range[arm_j]
        home = rng.mean(axis=1)
        key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "home")
        if key >= 0:   # the model's own neutral pose (Menagerie models have one)
            home = np.asarray(model.key_qpos[key])[model.jnt_qposadr[arm_j]].astype(float)
        return cls(
            xml_path=path, root_body=name(mujoco.mjtObj.mjOBJ_BODY, root), tcp_site=tcp_site,
            arm_joints=[name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in arm_j],
            arm_actuators=[name(mujoco.mjtObj.mjOBJ_ACTUATOR, arm_act[j]) for j in arm_j],
            gripper_joints=[name(mujoco.mjtObj.mjOBJ_JOINT, j) for j in grip_j],
            gripper_actuator=name(mujoco.mjtObj.mjOBJ_ACTUATOR, g),
            gripper_open=float(hi), gripper_closed=float(lo), max_opening=float(opening),
            home=home, vel_limits=np.full(len(arm_j), 2.0), acc_limits=np.full(len(arm_j), 5.0),
            hand_bodies=[name(mujoco.mjtObj.mjOBJ_BODY, bb) for bb in below],
        )

    def spec(self, visual: bool = True):
        """A fresh editable `mujoco.MjSpec` of the robot (TCP site ensured, keyframes removed).

        visual=False drops visual-only geoms and meshes (contype = conaffinity = 0): the same physics and
        collisions, compiled ~100x faster — for planning, IK and trials that render nothing.
        """
        import mujoco

        spec = mujoco.MjSpec.from_file(str(self.xml_path))
        ensure_tcp_site(spec)
        spec.compiler.discardvisual = not visual
        for k in list(spec.keys):  # keyframes would mismatch once the twin's free bodies are added
            spec.delete(k)
        return spec


def _is_descendant(model, body: int, ancestor: int) -> bool:
    while body != 0:
        if body == ancestor:
            return True
        body = int(model.body_parentid[body])
    return ancestor == 0


def ensure_tcp_site(spec) -> None:
    """Add the Panda TCP site to a spec whose `hand` body lacks one (e.g. a fresh Menagerie download)."""
    if any(s.name == TCP_SITE for s in spec.sites):
        return
    hand = spec.body("hand")
    if hand is not None:
        hand.add_site(name=TCP_SITE, pos=[0, 0, TCP_OFFSET_Z], size=[0.004, 0.004, 0.004], group=4)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m splattwin.robot.assets",
                                description="Provide the Franka Panda (MuJoCo Menagerie) model for the robot stage.")
    p.add_argument("--ensure", action="store_true", help="extract the Panda from the genesis-world wheel if missing")
    p.add_argument("--dest", type=Path, default=None, help="MENAGERIE_ROOT-style folder (default: %(default)s → "
                   "third_party/menagerie in a checkout)")
    p.add_argument("--wheel-dir", type=Path, default=None, help="where the wheel is cached")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    # ensure_panda's messages (log.info in the library) are this command's output, on stdout as before
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(logging.Formatter("%(message)s"))
    old = (log.level, log.propagate)
    if not args.quiet:
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False
    try:
        if args.ensure:
            ensure_panda(args.dest, args.wheel_dir, quiet=args.quiet)
        print(panda_model_path())
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    finally:
        log.removeHandler(handler)
        log.setLevel(old[0])
        log.propagate = old[1]
    return 0


if __name__ == "__main__":
    sys.exit(main())
