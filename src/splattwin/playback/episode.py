"""Episodes for policy learning in the LeRobot dataset layout (codebase v2.1), written and read without
the `lerobot` package (its install pulls torchvision and a CUDA stack; the layout is plain files):

    meta/info.json                  schema: fps, features, path templates, totals
    meta/episodes.jsonl             {episode_index, tasks, length} per episode
    meta/tasks.jsonl                {task_index, task}
    meta/episodes_stats.jsonl       per-episode min/max/mean/std/count of the numeric features
    data/chunk-000/episode_000000.parquet                       one row per frame (pyarrow)
    videos/chunk-000/observation.images.<camera>/episode_000000.mp4   one MP4 per camera (H.264)

Rows: observation.state = [7 arm joints (rad), gripper width (m)], action = [7 commanded joint targets
(rad), commanded gripper width (m)], timestamp (s from the episode start), frame_index, episode_index,
index (global), task_index, plus source_index (the `Rollout` sample the row was taken from) and
step_index (task step, -1 between steps). Frame k is the rollout's state at t0 + k / fps (the latest
sample at or before it), rendered from every camera: images and numbers are synchronous by construction.
LeRobot >= 0.4 reads v3.0; its converter (lerobot.datasets.v30.convert_dataset_v21_to_v30) takes this.

Every file is written atomically; the meta files last, so an episode whose meta is missing is simply
rewritten by the next run.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.playback.video import Mp4Writer, read_mp4

CODEBASE_VERSION = "v2.1"
CHUNKS_SIZE = 1000
DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
MAX_EPISODES = 1_000_000
MAX_ROWS = 2_000_000


def sample_indices(t: np.ndarray, fps: float) -> np.ndarray:
    """Rollout sample of each episode frame: the latest sample at or before t0 + k / fps."""
    t = np.asarray(t, float)
    if len(t) == 0:
        return np.zeros(0, np.int64)
    n = int(np.floor((t[-1] - t[0]) * fps + 1e-6)) + 1
    tk = t[0] + np.arange(n) / fps
    return np.clip(np.searchsorted(t, tk + 1e-9, side="right") - 1, 0, len(t) - 1).astype(np.int64)


def state_names(joint_names: list[str]) -> list[str]:
    return [*joint_names, "gripper_width"]


@dataclass
class Episode:
    """One episode read back: columns {name: array [T,...]}, videos {camera key: uint8 [T,H,W,3]},
    the episode's meta record and the dataset's info."""

    index: int
    columns: dict[str, np.ndarray]
    videos: dict[str, np.ndarray]
    meta: dict
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.columns["frame_index"]))


def _stats(a: np.ndarray) -> dict:
    a = np.asarray(a, float).reshape(len(a), -1)
    return {"min": a.min(0).tolist(), "max": a.max(0).tolist(), "mean": a.mean(0).tolist(),
            "std": a.std(0).tolist(), "count": [int(len(a))]}


def read_jsonl(path: Path) -> list[dict]:
    """The JSON objects of a JSON-lines file, one per non-blank line; [] when the file does not exist.
    Read within `limits.MAX_RECORD_BYTES` (an episode folder may come from someone else); InputError naming
    the file and line when a line is not a JSON object."""
    from splattwin.limits import MAX_RECORD_BYTES, read_text

    if not path.is_file():
        return []
    out = []
    for i, line in enumerate(read_text(path, "JSON-lines file", MAX_RECORD_BYTES).splitlines()):
        if line.strip():
            try:
                row = json.loads(line)
            except RecursionError:
                raise InputError(f"line {i + 1} is nested too deeply", path) from None
            except ValueError as e:  # JSONDecodeError, or an integer of more than 4300 digits
                raise InputError(f"line {i + 1} is not JSON: {str(e).split(';')[0]}", path) from None
            if not isinstance(row, dict):
                raise InputError(f"line {i + 1} is not a JSON object", path)
            out.append(row)
    return out


def _write_jsonl(path: Path, rows: list[dict]) -> None:
    io.write_text(path, "".join(json.dumps(r) + "\n" for r in rows))


def write_episode(root: str | Path, rollout, renderer, cameras: dict, fps: float = 15.0,
                  task: str = "pick and place", episode_index: int | None = None, robot_type: str = "franka_panda",
                  progress: bool = False, extra: dict | None = None) -> dict:
    """Render and write one episode of `rollout` (a `splattwin.robot.rollout.Rollout`) into the dataset
    folder `root` (created, or appended to).

    Args:
        renderer: a `PlaybackRenderer` with the robot. cameras: {key: Camera | EyeInHand}; the video
            feature is `observation.images.<key>`. fps: episode frame rate (frames are rollout samples).
        episode_index: None = the next free index. extra: more keys of the episode's record in
            meta/episodes.jsonl (the run's seed, success, perturbation).
    Returns: the episode's meta record ({episode_index, tasks, length, ...}).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from splattwin.playback.compositor import rollout_state

    root = Path(root)
    if not cameras:
        raise ValueError("at least one camera is needed")
    for k in cameras:
        if not str(k).replace("_", "").replace("-", "").isalnum():
            raise InputError(f"camera key {k!r} must be alphanumeric (with _ or -)")
    info_path = root / "meta" / "info.json"
    info = io.read_json(info_path) if info_path.is_file() else None
    episodes = read_jsonl(root / "meta" / "episodes.jsonl")
    tasks = read_jsonl(root / "meta" / "tasks.jsonl")
    stats = read_jsonl(root / "meta" / "episodes_stats.jsonl")
    if info is not None and abs(float(info.get("fps", fps)) - fps) > 1e-9:
        raise InputError(f"the dataset is at {info['fps']} fps, not {fps}", info_path)
    ep = len(episodes) if episode_index is None else int(episode_index)
    episodes = [e for e in episodes if e["episode_index"] != ep]
    stats = [s for s in stats if s["episode_index"] != ep]
    task_index = next((t["task_index"] for t in tasks if t["task"] == task), None)
    if task_index is None:
        task_index = len(tasks)
        tasks.append({"task_index": task_index, "task": task})
    start = sum(e["length"] for e in episodes if e["episode_index"] < ep)

    src = sample_indices(rollout.t, fps)
    T = len(src)
    chunk = ep // CHUNKS_SIZE
    names = state_names(rollout.joint_names or [f"joint{i + 1}" for i in range(rollout.q_arm.shape[1])])
    state = np.concatenate([rollout.q_arm[src], rollout.gripper_width[src, None]], 1).astype(np.float32)
    action = np.concatenate([rollout.action_q_arm[src], rollout.action_gripper[src, None]], 1).astype(np.float32)
    ts = (np.arange(T) / fps).astype(np.float32)

    # videos: every camera renders the same frame state
    writers = {k: Mp4Writer(root / VIDEO_PATH.format(episode_chunk=chunk, video_key=f"observation.images.{k}",
                                                     episode_index=ep), fps) for k in cameras}
    sizes = {}
    ok = False
    try:
        from splattwin.progress import track

        for k in track(range(T), f"episode {ep}: rendering {len(cameras)} cameras", unit="frame", enabled=progress):
            poses, rpose = rollout_state(rollout, int(src[k]))
            for key, cam in cameras.items():
                c = renderer.camera_for(cam, rpose)
                writers[key].write(renderer.render(c, poses, rpose).to_uint8())
                sizes[key] = (c.width, c.height)
        ok = True
    finally:
        for w in writers.values():
            w.close(ok=ok)

    cols = {
        "observation.state": pa.array(list(state), type=pa.list_(pa.float32(), state.shape[1])),
        "action": pa.array(list(action), type=pa.list_(pa.float32(), action.shape[1])),
        "timestamp": pa.array(ts, pa.float32()),
        "frame_index": pa.array(np.arange(T), pa.int64()),
        "episode_index": pa.array(np.full(T, ep), pa.int64()),
        "index": pa.array(start + np.arange(T), pa.int64()),
        "task_index": pa.array(np.full(T, task_index), pa.int64()),
        "source_index": pa.array(src, pa.int64()),
        "step_index": pa.array(rollout.step_index[src], pa.int64()),
    }
    table = pa.table(cols)
    dpath = root / DATA_PATH.format(episode_chunk=chunk, episode_index=ep)
    with io.atomic_path(dpath) as tmp:
        pq.write_table(table, tmp)

    features = {
        "observation.state": {"dtype": "float32", "shape": [len(names)], "names": names},
        "action": {"dtype": "float32", "shape": [len(names)], "names": names},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
        "source_index": {"dtype": "int64", "shape": [1], "names": None},
        "step_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    for key in cameras:
        w, h = sizes[key]
        features[f"observation.images.{key}"] = {
            "dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
            "info": {"video.fps": float(fps), "video.height": h, "video.width": w, "video.channels": 3,
                     "video.codec": "h264", "video.pix_fmt": "yuv420p", "video.is_depth_map": False,
                     "has_audio": False}}
    if info is not None and set(info.get("features", {})) != set(features):
        raise InputError("the dataset's features differ from this episode's (other cameras?)", info_path)
    meta = {**(extra or {}), "episode_index": ep, "tasks": [task], "length": T}
    episodes.append(meta)
    episodes.sort(key=lambda e: e["episode_index"])
    stats.append({"episode_index": ep, "stats": {"observation.state": _stats(state), "action": _stats(action),
                                                 "timestamp": _stats(ts)}})
    stats.sort(key=lambda e: e["episode_index"])
    n_ep = len(episodes)
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": n_ep,
        "total_frames": int(sum(e["length"] for e in episodes)), "total_tasks": len(tasks),
        "total_videos": n_ep * len(cameras), "total_chunks": max(e["episode_index"] for e in episodes) // CHUNKS_SIZE + 1,
        "chunks_size": CHUNKS_SIZE, "fps": float(fps), "splits": {"train": f"0:{n_ep}"},
        "data_path": DATA_PATH, "video_path": VIDEO_PATH, "features": features,
    }
    _write_jsonl(root / "meta" / "tasks.jsonl", tasks)
    _write_jsonl(root / "meta" / "episodes_stats.jsonl", stats)
    _write_jsonl(root / "meta" / "episodes.jsonl", episodes)
    io.write_json(info_path, info)
    return meta


def _confined(root: Path, rel: str) -> Path:
    p = (root / rel).resolve()
    try:
        p.relative_to(root.resolve())
    except ValueError:
        raise InputError(f"path {rel!r} points outside the dataset", root / "meta" / "info.json") from None
    return p


def read_episode(root: str | Path, episode_index: int, videos: bool = True) -> Episode:
    """Read one episode back (parquet columns as numpy, videos decoded). InputError on a malformed dataset."""
    import pyarrow.parquet as pq

    root = Path(root)
    info_path = root / "meta" / "info.json"
    info = io.read_json(info_path, missing="not a LeRobot dataset (no meta/info.json)")
    if not isinstance(info, dict) or info.get("codebase_version") not in ("v2.0", "v2.1"):
        raise InputError(f"unsupported dataset version {info.get('codebase_version') if isinstance(info, dict) else '?'} "
                         "(reads v2.0/v2.1)", info_path)
    ep = int(episode_index)
    if not 0 <= ep < MAX_EPISODES:
        raise InputError(f"episode index {ep} out of range")
    metas = [e for e in read_jsonl(root / "meta" / "episodes.jsonl") if e.get("episode_index") == ep]
    if not metas:
        raise InputError(f"no episode {ep} in meta/episodes.jsonl", root / "meta" / "episodes.jsonl")
    chunk = ep // int(info.get("chunks_size", CHUNKS_SIZE))
    try:
        dpath = _confined(root, str(info.get("data_path", DATA_PATH)).format(episode_chunk=chunk, episode_index=ep))
    except (KeyError, IndexError, ValueError) as e:
        raise InputError(f"malformed data_path: {e}", info_path) from e
    if not dpath.is_file():
        raise InputError("episode data file missing", dpath)
    try:
        pf = pq.ParquetFile(dpath)
        if pf.metadata.num_rows > MAX_ROWS:
            raise InputError(f"episode has {pf.metadata.num_rows} rows (at most {MAX_ROWS})", dpath)
        table = pf.read()
    except (OSError, ValueError) as e:   # pyarrow's errors derive from these
        raise InputError(f"not a readable parquet file: {e}", dpath) from e
    columns = {}
    for name in table.column_names:
        col = table.column(name).to_pylist() if str(table.schema.field(name).type).startswith(("fixed_size_list", "list")) \
            else table.column(name).to_numpy()
        columns[name] = np.asarray(col)
    if int(metas[0].get("length", -1)) != len(table):
        raise InputError(f"episode {ep}: meta says {metas[0].get('length')} frames, data has {len(table)}", dpath)
    vids = {}
    if videos:
        for key, feat in info.get("features", {}).items():
            if not isinstance(feat, dict) or feat.get("dtype") != "video":
                continue
            try:
                vp = _confined(root, str(info.get("video_path", VIDEO_PATH)).format(
                    episode_chunk=chunk, video_key=key, episode_index=ep))
            except (KeyError, IndexError, ValueError) as e:
                raise InputError(f"malformed video_path: {e}", info_path) from e
            h, w = (int(x) for x in feat["shape"][:2])
            vids[key] = read_mp4(vp, size=(w, h), max_frames=MAX_ROWS)
    return Episode(ep, columns, vids, metas[0], info)


def check_episode(episode: Episode, rollout, renderer=None, cameras: dict | None = None,
                  fps: float | None = None, min_psnr: float = 30.0) -> int:
    """Check an episode read back against its source rollout, frame by frame; returns the number of frames
    checked, raises AssertionError at the first mismatch: the frame count (sample_indices at the dataset's
    fps), every row's state, action, timestamp, indices against the rollout sample it names, every video's
    frame count and, with a renderer and the cameras, every decoded frame against a fresh render of that
    state (PSNR >= min_psnr dB: H.264 is lossy)."""
    from splattwin.playback.compositor import rollout_state

    fps = float(fps or episode.info.get("fps"))
    src = sample_indices(rollout.t, fps)
    c = episode.columns
    if len(episode) != len(src):
        raise AssertionError(f"episode has {len(episode)} frames, the rollout at {fps} fps {len(src)}")
    if not np.array_equal(c["source_index"], src):
        raise AssertionError("source_index differs from the rollout sampling")
    state = np.stack(c["observation.state"]).astype(np.float64)
    action = np.stack(c["action"]).astype(np.float64)
    checked = 0
    for k, s in enumerate(src):
        exp_state = np.append(rollout.q_arm[s], rollout.gripper_width[s])
        exp_action = np.append(rollout.action_q_arm[s], rollout.action_gripper[s])
        if not np.allclose(state[k], exp_state, atol=1e-6, rtol=1e-6):
            raise AssertionError(f"frame {k}: state {state[k]} != rollout {exp_state}")
        if not np.allclose(action[k], exp_action, atol=1e-6, rtol=1e-6):
            raise AssertionError(f"frame {k}: action {action[k]} != rollout {exp_action}")
        if abs(float(c["timestamp"][k]) - k / fps) > 1e-5 or int(c["frame_index"][k]) != k:
            raise AssertionError(f"frame {k}: timestamp/frame_index {c['timestamp'][k]}/{c['frame_index'][k]}")
        if int(c["step_index"][k]) != int(rollout.step_index[s]):
            raise AssertionError(f"frame {k}: step_index {c['step_index'][k]} != {rollout.step_index[s]}")
        for key, v in episode.videos.items():
            if len(v) != len(src):
                raise AssertionError(f"{key}: {len(v)} video frames for {len(src)} rows")
            if renderer is not None and cameras is not None:
                cam_key = key.removeprefix("observation.images.")
                poses, rpose = rollout_state(rollout, int(s))
                cam = renderer.camera_for(cameras[cam_key], rpose)
                ref = renderer.render(cam, poses, rpose).rgb
                mse = float(np.mean((v[k].astype(np.float64) / 255 - ref) ** 2))
                psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
                if psnr < min_psnr:
                    raise AssertionError(f"{key} frame {k}: {psnr:.1f} dB against a fresh render of its state")
        checked += 1
    return checked
