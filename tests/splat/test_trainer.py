from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from splattwin.capture import Camera, Dataset, Frame, look_at
from splattwin.capture import load_dataset
from splattwin.capture.nerfstudio import write as write_transforms
from splattwin.io import write_image
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.splat.rasterize import rasterization
from splattwin.splat.trainer import TrainConfig, Trainer, train

W, H = 48, 36


def gt_gaussians(seed: int = 0) -> Gaussians:
    """A small coloured scene: blobs above a textured floor patch, all within 0.3 m of the origin."""
    rng = np.random.default_rng(seed)
    n_blob = 24
    blob = rng.uniform([-0.2, -0.2, 0.02], [0.2, 0.2, 0.15], size=(n_blob, 3))
    gx, gy = np.meshgrid(np.linspace(-0.3, 0.3, 10), np.linspace(-0.3, 0.3, 10))
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    means = np.concatenate([blob, floor])
    n = len(means)
    scales = np.concatenate([rng.uniform(0.02, 0.05, (n_blob, 3)), np.tile([0.04, 0.04, 0.004], (len(floor), 1))])
    cols = np.concatenate([rng.uniform(0.1, 0.9, (n_blob, 3)),
                           np.where(((np.arange(len(floor)) + np.arange(len(floor)) // 10) % 2)[:, None] == 0,
                                    [0.8, 0.7, 0.5], [0.3, 0.35, 0.4])])
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    return Gaussians(means, quats, scales, np.full(n, 0.9), rgb_to_sh0(cols)[:, None, :])


def ring_cameras(n: int, width: int = W, height: int = H, radius: float = 0.7, height_z: float = 0.45,
                 offset: float = 0.0) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n + offset
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height_z])
        cams.append(Camera.from_fov(math.radians(60), width, height, look_at(eye, np.zeros(3)), name=f"v{i:02d}"))
    return cams


def render_gaussians(g: Gaussians, cam: Camera, backend: str = "cpu") -> np.ndarray:
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    img, _, _ = rasterization(t(g.means), t(g.quats), t(g.scales), t(g.opacities), t(g.sh),
                              t(cam.T_cam_world)[None], t(cam.K)[None], cam.width, cam.height,
                              sh_degree=g.sh_degree, backend=backend)
    return img[0].clamp(0, 1).numpy()


def make_dataset(root: Path, n_train: int = 8, n_heldout: int = 2, seed: int = 0, width: int = W,
                 height: int = H, point_noise: float = 0.01) -> Path:
    """Render the synthetic scene into a nerfstudio dataset folder (transforms.json + PNGs + points)."""
    g = gt_gaussians(seed)
    cams = ring_cameras(n_train, width, height) + ring_cameras(n_heldout, width, height, offset=0.3)
    frames = []
    for i, cam in enumerate(cams):
        split = "train" if i < n_train else "heldout"
        cam.name = f"{split}_{i:03d}"
        img = render_gaussians(g, cam)
        p = write_image(root / "images" / f"{cam.name}.png", (img * 255 + 0.5).astype(np.uint8))
        frames.append(Frame(image_path=p, camera=cam, split=split))
    rng = np.random.default_rng(seed)
    pts = g.means + rng.normal(0, point_noise, g.means.shape)
    ds = Dataset(root=root, frames=frames, has_poses=True, points_xyz=pts,
                 points_rgb=(np.clip(g.colors, 0, 1) * 255).astype(np.uint8))
    write_transforms(ds, root / "transforms.json")
    return root


def half_image_masks(frames, label: int = 1, name: str = "thing"):
    """A MaskSet with one object covering the top half of every frame's image (the image rows above
    height // 2), for the semantics tests on `make_dataset`'s scene."""
    from splattwin.semantics.masks import MaskSet

    ms = MaskSet()
    for f in frames:
        m = np.zeros((f.camera.height, f.camera.width), bool)
        m[: f.camera.height // 2] = True
        ms.add(f.name, label, m, name=name)
    return ms


def interrupted_then_resumed(ds, out: Path, cfg, at_step: int):
    """Train into `out`, stopped by Ctrl-C at `at_step`, then resumed from its last checkpoint: the result."""
    def stop(info):
        if info["step"] == at_step:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(ds, out, cfg, callback=stop)
    return train(ds, out, cfg, resume=True)


def strict_json(path: Path):
    """The JSON file at `path`, refusing the non-standard NaN/Infinity tokens Python's json writes by default."""
    def refuse(token):
        raise AssertionError(f"{path.name} holds {token}: not standard JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def assert_resumes_to(ds, out: Path, cfg, reference) -> None:
    """Resuming the interrupted run in `out` reaches `reference` (an uninterrupted run) bit for bit, with the
    same training curve and final figures (the moving averages are checkpointed, not restarted)."""
    c = Trainer(ds, out, cfg).run(resume=True)
    assert c.steps == cfg.iters
    for k in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(c.gaussians, k), getattr(reference.gaussians, k))
    assert c.history == reference.history
    assert (c.final_loss, c.final_psnr) == (reference.final_loss, reference.final_psnr)
    assert strict_json(out / "train.json")["history"] == reference.history


def drop_split(root: Path) -> Path:
    """Remove every train/held-out mark from root/transforms.json (a capture without its own split)."""
    meta = json.loads((root / "transforms.json").read_text())
    for k in ("train_filenames", "val_filenames", "test_filenames"):
        meta.pop(k, None)
    for fr in meta["frames"]:
        fr.pop("split", None)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("synth"))


def tiny_config(**kw) -> TrainConfig:
    # sparse_views=0: these tests pin the dense defaults (the sparse profile has its own tests)
    base = dict(iters=120, sh_degree=1, checkpoint_every=0, progress=False, backend="cpu", max_gaussians=2000,
                sparse_views=0)
    base.update(kw)
    return TrainConfig(**base)


def test_training_reduces_loss_and_writes_ply(synth, tmp_path):
    ds = load_dataset(synth)
    res = train(ds, tmp_path / "out", tiny_config(iters=200))
    h = res.history
    assert res.init_method == "sfm" and res.steps == 200
    first = np.mean([e["loss"] for e in h[:2]])
    assert res.final_loss < 0.6 * first
    assert res.final_psnr > h[0]["psnr"] + 5 and res.final_psnr > 22
    g = Gaussians.load_ply(tmp_path / "out" / "point_cloud.ply")
    assert len(g) == len(res.gaussians) and g.sh_degree == 1
    assert (tmp_path / "out" / "train.json").is_file()
    from PIL import Image
    assert Image.open(tmp_path / "out" / "train_curves.png").size == (640, 240)


def test_training_removes_the_earlier_splats_heldout_metrics(tmp_path):
    """`splattwin train` into a built twin's splat/ left splat/eval/metrics.json and the held-out comparison
    pictures of the splats it replaced: the report showed that PSNR as the new model's. A new
    point_cloud.ply takes away what the evaluation wrote (by the names its metrics.json lists), only that;
    an eval folder left empty goes too."""
    import json

    from splattwin.splat.eval import evaluate

    ds = make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    out = tmp_path / "out"
    train(load_dataset(ds), out, tiny_config(iters=5))
    evaluate(out, ds, out / "eval", progress=False)
    pictures = [v["image"] for v in json.loads((out / "eval" / "metrics.json").read_text())["views"]]
    assert len(pictures) == 2 and all((out / "eval" / p).is_file() for p in pictures)
    (out / "eval" / "notes.txt").write_text("mine")
    (out / "eval" / "mine.png").write_bytes(b"not the evaluation's")
    train(load_dataset(ds), out, tiny_config(iters=6))
    assert (out / "point_cloud.ply").is_file() and not (out / "eval" / "metrics.json").exists()
    assert not any((out / "eval" / p).exists() for p in pictures)
    assert (out / "eval" / "notes.txt").read_text() == "mine" and (out / "eval" / "mine.png").is_file()
    evaluate(out, ds, out / "eval", progress=False)
    (out / "eval" / "notes.txt").unlink()
    (out / "eval" / "mine.png").unlink()
    train(load_dataset(ds), out, tiny_config(iters=7))
    assert not (out / "eval").exists()


def test_progress_in_a_redirected_log_is_plain_lines(synth, tmp_path, capsys, monkeypatch):
    """stderr not a terminal (a log file, CI): a start line, lines every interval with the figures, an end
    line; no carriage-return redraws (tqdm wrote one per 0.1 s)."""
    monkeypatch.setenv("SPLATTWIN_PROGRESS_INTERVAL", "0.000001")   # a line at every update
    train(load_dataset(synth), tmp_path / "out", tiny_config(iters=30, progress=True))
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("train: ")]
    assert lines[0].startswith("train: 0/30 it (0 %)")
    assert any(ln.startswith("train: 10/30 it (33 %)") and "ETA" in ln and "psnr" in ln and "gaussians" in ln
               for ln in lines)
    assert lines[-1].startswith("train: 30/30 it done in")


@pytest.mark.parametrize("drop_rate", [0.0, 0.4])
def test_deterministic_and_resume_equivalent(synth, tmp_path, drop_rate):
    """Same options, same result; a run killed after a checkpoint resumes to the uninterrupted result (with
    DropGaussian's random masks too: their generator is checkpointed)."""
    ds = load_dataset(synth)
    cfg = tiny_config(iters=60, checkpoint_every=20, drop_rate=drop_rate)
    a = train(ds, tmp_path / "a", cfg)
    b = train(ds, tmp_path / "b", cfg)
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    np.testing.assert_array_equal(a.gaussians.sh, b.gaussians.sh)

    class Killed(Exception):
        pass

    def kill(info):
        if info["step"] == 47:  # after the checkpoint at 40: steps 41..47 are lost and redone
            raise Killed

    with pytest.raises(Killed):
        train(ds, tmp_path / "c", cfg, callback=kill)
    assert not (tmp_path / "c" / "point_cloud.ply").exists()
    assert sorted(p.name for p in (tmp_path / "c" / "checkpoints").iterdir()) == ["ckpt_000020.safetensors", "ckpt_000040.safetensors"]
    assert_resumes_to(ds, tmp_path / "c", cfg, a)


def test_resuming_a_finished_run_reports_its_figures(synth, tmp_path):
    """--resume on a finished run runs no step and reports the run's own final loss/PSNR and training time
    (it used to write NaN, invalid JSON, and the 0.2 s the resume took); train.json is strict JSON."""
    ds = load_dataset(synth)
    cfg = tiny_config(iters=40, checkpoint_every=20)
    a = train(ds, tmp_path / "a", cfg)
    first = strict_json(tmp_path / "a" / "train.json")
    assert first["resumed_at_step"] is None and first["wall_s"] == round(a.wall_s, 3)
    b = train(ds, tmp_path / "a", cfg, resume=True)
    rec = strict_json(tmp_path / "a" / "train.json")
    assert b.steps == 40 and b.resumed_at_step == 40 and rec["resumed_at_step"] == 40
    assert (b.final_loss, b.final_psnr) == (a.final_loss, a.final_psnr)
    assert (rec["train_loss"], rec["train_psnr"]) == (first["train_loss"], first["train_psnr"])
    assert math.isfinite(rec["train_psnr"]) and rec["history"] == first["history"]
    # the training time behind the result: the original run's (checkpointed at its last step), not the resume's
    assert 0.9 * a.wall_s <= b.wall_s <= a.wall_s + 5.0
    np.testing.assert_array_equal(b.gaussians.means, a.gaussians.means)


def test_a_fresh_run_removes_an_earlier_runs_checkpoints(synth, tmp_path):
    """A run that starts over (no --resume) into a folder with a finished run's checkpoints removes them:
    left there, the finished step-40 checkpoint outranked the new run's and a later --resume (after a kill)
    continued the old run instead of the new one."""
    ds = load_dataset(synth)
    cfg = tiny_config(iters=40, checkpoint_every=20)
    train(ds, tmp_path / "a", cfg)

    def stop(info):
        if info["step"] == 25:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(ds, tmp_path / "a", cfg, callback=stop)
    names = sorted(p.name for p in (tmp_path / "a" / "checkpoints").iterdir())
    assert names == ["ckpt_000020.safetensors"]
    assert train(ds, tmp_path / "a", cfg, resume=True).resumed_at_step == 20


def test_ctrl_c_finishes_the_step_saves_and_resumes_to_the_same_result(synth, tmp_path, terminal_ctrl_c):
    """A real SIGINT mid-run: the step in progress completes, a checkpoint of that step is written (not only
    the periodic ones: steps 41..47 are kept), KeyboardInterrupt ends the run, and --resume reaches the
    uninterrupted result bit for bit."""
    import os
    import signal

    ds = load_dataset(synth)
    cfg = tiny_config(iters=60, checkpoint_every=20)
    a = train(ds, tmp_path / "a", cfg)

    def ctrl_c(info):
        if info["step"] == 47:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        train(ds, tmp_path / "c", cfg, callback=ctrl_c)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler   # handler restored
    names = sorted(p.name for p in (tmp_path / "c" / "checkpoints").iterdir())
    assert names == ["ckpt_000040.safetensors", "ckpt_000047.safetensors"]
    assert_resumes_to(ds, tmp_path / "c", cfg, a)


def _diverged(err) -> bool:
    """`err` is the trainer's TrainingDiverged (by name: the test shows what was raised instead)."""
    return type(err).__name__ == "TrainingDiverged" and isinstance(err, RuntimeError)


def _poisoned_run(ds, out: Path, name: str, at_step: int, cfg):
    """Train into `out`, one entry of model parameter `name` set to NaN after step `at_step` (as a diverging
    update would): (the trainer, the exception the run raised or None, the steps that completed)."""
    tr = Trainer(ds, out, cfg)
    steps = []

    def poison(info):
        steps.append(info["step"])
        if info["step"] == at_step:
            with torch.no_grad():
                tr.model.params[name].view(-1)[0] = float("nan")

    try:
        tr.run(callback=poison)
    except Exception as e:  # noqa: BLE001 - the test asserts on its type
        return tr, e, steps
    return tr, None, steps


def test_a_non_finite_loss_stops_training_at_that_step_and_keeps_the_good_checkpoint(synth, tmp_path):
    """One NaN colour poisons the pixels it covers, the loss and every gradient there; Adam then wrote NaN into
    every Gaussian those pixels see and the run went on to its end (the loss finite again: the CPU kernels skip
    NaN geometry), checkpointed the NaN state over the good checkpoints and failed only when writing the splat
    ("124 Gaussians have non-finite means", exit 2, no step): unresumable. Now the first non-finite loss stops
    the run with a message naming the step, the view and the parameter, before any update."""
    ds = load_dataset(synth)
    cfg = tiny_config(iters=40, checkpoint_every=10)
    tr, err, steps = _poisoned_run(ds, tmp_path / "a", "sh0", 12, cfg)
    assert _diverged(err), err
    msg = str(err)
    assert "the loss of step 13 (view 'train_" in msg and "is nan" in msg
    assert "sh0 (1 of " in msg and "first at row 0" in msg
    assert steps[-1] == 12 and tr.step == 12  # step 13 made no update: only the poisoned entry is NaN
    assert int((~torch.isfinite(tr.model.params["sh0"])).sum()) == 1
    names = sorted(p.name for p in (tmp_path / "a" / "checkpoints").iterdir())
    assert names == ["ckpt_000010.safetensors"] and "ckpt_000010.safetensors, is finite" in msg
    assert train(ds, tmp_path / "a", cfg, resume=True).resumed_at_step == 10  # the good state resumes


def test_non_finite_geometry_is_caught_before_it_is_checkpointed(synth, tmp_path):
    """A NaN mean leaves the loss finite (the Gaussian is not drawn), so it used to be checkpointed (the good
    checkpoints deleted, --resume refusing the NaN ones) and reported only when the splat was written, as bad
    input. The checkpoint and the end of training now refuse a non-finite model with a clear error."""
    ds = load_dataset(synth)
    tr, err, steps = _poisoned_run(ds, tmp_path / "a", "means", 12, tiny_config(iters=40, checkpoint_every=10))
    assert _diverged(err), err
    assert "non-finite model parameters after step 20: means (" in str(err)
    assert sorted(p.name for p in (tmp_path / "a" / "checkpoints").iterdir()) == ["ckpt_000010.safetensors"]
    # without checkpoints: the end of training, not the splat writer, says what happened
    tr, err, steps = _poisoned_run(ds, tmp_path / "b", "means", 12, tiny_config(iters=30, checkpoint_every=0))
    assert _diverged(err) and "after step 30: means" in str(err), err
    assert steps[-1] == 30 and not (tmp_path / "b" / "point_cloud.ply").exists()


def test_drop_rate_hides_gaussians_and_compensates_opacity(synth, tmp_path):
    """DropGaussian: the training render at rate r equals the reference rasterization of the model with a
    Bernoulli(1 - r) subset kept (drawn from the trainer's own generator) at opacity / (1 - r); the rate
    ramps linearly over the run; rate 0 draws nothing (default training unchanged)."""
    ds = load_dataset(synth)
    t = Trainer(ds, tmp_path / "t", tiny_config(iters=40, drop_rate=0.5))
    t._fresh_state()
    state = t.drop_gen.get_state()
    img, alpha, _ = t.render(0, sh_degree=0, drop=0.5)
    gen = torch.Generator()
    gen.set_state(state)
    act = t.model.activated()
    keep = torch.rand(act["opacities"].shape, generator=gen) >= 0.5
    assert 0.3 < keep.float().mean() < 0.7
    v = t.levels[0][0]
    ref, ref_alpha, _ = rasterization(act["means"], act["quats"], act["scales"], act["opacities"] * keep / 0.5,
                                      act["sh"], t.viewmats[0:1], t.Ks_levels[0][0:1], v.camera.width,
                                      v.camera.height, sh_degree=0, backgrounds=t.bg, backend=t.backend,
                                      rasterize_mode=t.cfg.rasterize_mode, eps2d=0.3)
    torch.testing.assert_close(img, ref[0])
    torch.testing.assert_close(alpha, ref_alpha[0])
    full, _, _ = t.render(0, sh_degree=0)
    assert (img - full).abs().max() > 0.05        # something was hidden
    # the ramp: no draw at step 0, the generator advances once per step after
    t2 = Trainer(ds, tmp_path / "t2", tiny_config(iters=40, drop_rate=0.5))
    t2._fresh_state()
    s0 = t2.drop_gen.get_state()
    t2.train_step()
    assert torch.equal(t2.drop_gen.get_state(), s0)
    t2.train_step()
    assert not torch.equal(t2.drop_gen.get_state(), s0)
    t3 = Trainer(ds, tmp_path / "t3", tiny_config(iters=40))
    t3._fresh_state()
    s3 = t3.drop_gen.get_state()
    for _ in range(3):
        t3.train_step()
    assert torch.equal(t3.drop_gen.get_state(), s3)


@pytest.mark.parametrize("rate", [1.0, 1.5, -0.5])
def test_drop_rate_outside_0_1_is_refused(synth, tmp_path, rate):
    from splattwin.errors import InputError

    with pytest.raises(InputError, match="--drop-rate must be in"):
        Trainer(load_dataset(synth), tmp_path / "t", tiny_config(drop_rate=rate))


def test_densification_runs_in_training(synth, tmp_path):
    ds = load_dataset(synth)
    cfg = tiny_config(iters=100, init="random", init_points=300)
    res = train(ds, tmp_path / "d", cfg)
    counts = [e["n"] for e in res.history]
    assert max(counts) > 300 or min(counts) < 300  # the Gaussian set changed
    assert len(res.gaussians) <= cfg.max_gaussians


def test_refine_poses_outputs_and_resume(synth, tmp_path):
    """Joint pose refinement: writes refined poses, moves them a little, and resumes exactly.
    (Recovery of a known perturbation is tested in test_pose_refine.py.)"""
    import json

    ds = load_dataset(synth)
    cfg = tiny_config(iters=40, refine_poses=True, pose_start=0.25, checkpoint_every=20, densify=False)
    a = train(ds, tmp_path / "a", cfg)
    poses = json.loads((tmp_path / "a" / "refined_poses.json").read_text())["poses"]
    assert set(poses) == {f.name for f in ds.train()}
    moved = [np.abs(np.array(poses[f.name]) - f.camera.T_world_cam).max() for f in ds.train()]
    assert 0 < max(moved) < 0.05

    b = interrupted_then_resumed(ds, tmp_path / "b", cfg, at_step=27)
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    assert a.refined_T_world_cam == b.refined_T_world_cam


def test_depth_loss_analytic_and_masked():
    from splattwin.splat.trainer import depth_loss

    gt = torch.tensor([[1.0, 2.0], [float("inf"), 4.0]])
    alpha = torch.tensor([[0.9, 0.9], [0.9, 0.2]])
    depth = torch.tensor([[1.1, 1.5], [7.0, 9.0]], requires_grad=True)
    loss = depth_loss(depth, alpha, gt)
    # only (0,0) and (0,1) count: inf depth and alpha <= 0.5 are excluded
    assert float(loss.detach()) == pytest.approx((0.1 / 1.0 + 0.5 / 2.0) / 2)
    loss.backward()
    torch.testing.assert_close(depth.grad, torch.tensor([[0.5, -0.25], [0.0, 0.0]]))
    assert float(depth_loss(depth, torch.zeros(2, 2), gt).detach()) == 0.0


def test_depth_supervision_pulls_geometry_onto_measured_depth(scene_small, tmp_path):
    """From a random init, 120 steps with the depth loss leave a much smaller rendered-depth error than
    the same steps without it (the photometric loss alone barely fixes geometry that fast)."""
    from splattwin.splat.trainer import depth_loss, load_views

    ds = load_dataset(scene_small)
    views = load_views(ds.train(), 2, depth=True)
    assert all(v.depth is not None and v.depth.shape == v.image.shape[:2] for v in views)
    cfg = tiny_config(iters=120, resolution=2, sh_degree=0, init="random", init_points=2000, densify=False)
    err = {}
    for lam in (0.0, 0.5):
        tr = Trainer(ds, tmp_path / str(lam), TrainConfig(**{**cfg.__dict__, "depth_lambda": lam}))
        tr.run()
        with torch.no_grad():
            err[lam] = np.mean([float(depth_loss(img[..., 3], a[..., 0], v.depth))
                                for v, (img, a, _) in ((v, tr.render(i, render_mode="RGB+ED"))
                                                       for i, v in enumerate(views))])
    assert err[0.5] < 0.5 * err[0.0], err


@pytest.mark.parametrize("mode", ["relative", "inverse"])
def test_depth_holes_never_pull_depth(scene_small, tmp_path, mode):
    """A D435 writes 0 where it has no reading: a run whose depth maps are all holes (0, as a 16-bit PNG
    writes them; NaN and inf too) with the depth loss on trains exactly as the run without depth loss."""
    import shutil

    ds0 = load_dataset(scene_small)
    holed = tmp_path / "holed"
    shutil.copytree(scene_small, holed)
    for i, f in enumerate(ds0.frames):
        d = np.load(f.depth_path)
        d[:] = (0.0, np.nan, np.inf)[i % 3]
        np.save(holed / f.depth_path.relative_to(scene_small), d)
    cfg = tiny_config(iters=30, resolution=2, sh_degree=0, init="random", init_points=800, densify=False)
    res = {}
    for lam, root in ((0.0, scene_small), (1.0, holed)):
        ds = load_dataset(root)
        tr = Trainer(ds, tmp_path / f"out_{lam}", TrainConfig(**{**cfg.__dict__, "depth_lambda": lam,
                                                                 "depth_mode": mode}))
        assert lam == 0 or all(v.depth is not None and torch.isinf(v.depth).all() for v in tr.views)
        res[lam] = tr.run().gaussians
    np.testing.assert_array_equal(np.asarray(res[1.0].means), np.asarray(res[0.0].means))
    np.testing.assert_array_equal(np.asarray(res[1.0].opacities), np.asarray(res[0.0].opacities))


def test_opacity_reg_lowers_the_mean_opacity(scene_small, tmp_path):
    """gsplat's opacity_reg: the same short run with the penalty ends with fainter Gaussians on average."""
    ds = load_dataset(scene_small)
    cfg = tiny_config(iters=60, resolution=2, sh_degree=0, init="depth", init_points=1500, densify=False)
    mean_op = {}
    for reg in (0.0, 0.5):
        res = Trainer(ds, tmp_path / str(reg), TrainConfig(**{**cfg.__dict__, "opacity_reg": reg})).run()
        mean_op[reg] = float(res.gaussians.opacities.mean())
    assert mean_op[0.5] < mean_op[0.0] - 0.02, mean_op


def test_resolution_level_schedule():
    from splattwin.splat.trainer import resolution_level

    # 2 levels, 10 % of 3000 steps each: 1/4 for steps 0-299, 1/2 for 300-599, full size from 600
    lv = [resolution_level(s, 3000, 2, 0.1) for s in (0, 299, 300, 599, 600, 2999)]
    assert lv == [2, 2, 1, 1, 0, 0]
    assert [resolution_level(s, 1000, 1, 0.05) for s in (0, 49, 50)] == [1, 1, 0]
    assert {resolution_level(s, 3000, 0, 0.1) for s in range(0, 3000, 7)} == {0}  # off
    assert {resolution_level(s, 3000, 2, 0.0) for s in range(0, 3000, 7)} == {0}  # off
    assert resolution_level(0, 5, 3, 0.01) == 3 and resolution_level(1, 5, 3, 0.01) == 2  # blocks >= 1 step


def test_downscale_view_averages_pixels_and_scales_the_camera():
    from splattwin.splat.trainer import TrainView, downscale_view

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (36, 48, 3)).astype(np.float32)
    depth = rng.uniform(1, 2, (36, 48)).astype(np.float32)
    cam = Camera.from_fov(math.radians(60), 48, 36, np.eye(4))
    small = downscale_view(TrainView("v", torch.from_numpy(img), cam, torch.from_numpy(depth)), 4)
    assert small.image.shape == (9, 12, 3) and small.depth.shape == (9, 12)
    want = img.reshape(9, 4, 12, 4, 3).mean(axis=(1, 3))  # box filter = block means (no 8-bit rounding)
    np.testing.assert_allclose(small.image.numpy(), want, atol=1e-6)
    assert set(np.unique(small.depth.numpy())) <= set(np.unique(depth))  # nearest samples, not blends
    assert (small.camera.width, small.camera.height) == (12, 9)
    np.testing.assert_allclose(small.camera.K[:2], cam.K[:2] / 4)
    # the same ray through the same relative image position
    p = np.array([[0.05, -0.03, 1.0]])
    np.testing.assert_allclose(small.camera.project(p)[0], cam.project(p)[0] / 4, atol=1e-9)


def test_coarse_levels_render_the_training_size_model_on_a_coarser_grid(synth, tmp_path):
    """Level k renders with the low-pass eps2d / 4^k (coarse px^2): a Gaussian's footprint is the one the
    full-size render gives it, so coarse-level alpha mass x 4^k matches the full-size mass; the full eps2d
    at coarse levels would inflate small Gaussians (16x more dilation at 1/4 size)."""
    ds = load_dataset(make_dataset(tmp_path / "big", width=128, height=96))
    tr = Trainer(ds, tmp_path / "o", tiny_config(num_downscales=2, downscale_every=0.1))
    tr._fresh_state()
    assert len(tr.levels) == 2  # 1/4 would leave 24 px (< MIN_LEVEL_SIDE): capped at 1/2
    assert [tr.level_at(s) for s in (0, 11, 12, 23, 24)] == [1, 1, 1, 1, 0]  # levels 2 (capped to 1), 1, 0
    assert tuple(tr.levels[1][0].image.shape) == (48, 64, 3)
    with torch.no_grad():
        full = float(tr.render(0, level=0)[1].sum())
        coarse = float(tr.render(0, level=1)[1].sum()) * 4
        act = tr.model.activated()
        v = tr.levels[1][0]
        _, a_bad, _ = rasterization(act["means"], act["quats"], act["scales"], act["opacities"], act["sh"],
                                    tr.viewmats[:1], tr.Ks_levels[1][:1], v.camera.width, v.camera.height,
                                    sh_degree=0, backend="cpu", eps2d=0.3)
    bad = float(a_bad.sum()) * 4
    assert abs(coarse - full) < 0.03 * full
    assert bad > coarse + 3 * abs(coarse - full)


def test_coarse_to_fine_training_trains_at_each_level_and_is_deterministic(synth, tmp_path):
    ds = load_dataset(make_dataset(tmp_path / "big", width=128, height=96))
    sizes: list[tuple[int, int]] = []
    import splattwin.splat.trainer as T

    real = T.rasterization

    def spy(*a, **k):
        sizes.append((a[7], a[8]))
        return real(*a, **k)

    from splattwin.splat.strategy import DefaultStrategy

    class Recording(DefaultStrategy):  # the hooks get the size of the level rendered (means2d's pixels)
        def step_pre_backward(self, model, state, step, info):
            seen.append((info["width"], info["height"]))
            super().step_pre_backward(model, state, step, info)

    seen: list = []
    cfg = tiny_config(iters=40, num_downscales=1, downscale_every=0.25)
    T.rasterization = spy
    try:
        a = train(ds, tmp_path / "a", cfg, strategy=Recording(cfg.densify_config()))
    finally:
        T.rasterization = real
    assert sizes[:10] == [(64, 48)] * 10 and sizes[10:] == [(128, 96)] * 30
    assert seen == sizes
    b = train(ds, tmp_path / "b", cfg)
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    assert a.final_psnr > a.history[0]["psnr"]


def test_default_capacity_scales_with_the_image_side(synth, tmp_path):
    from splattwin.splat.resolution import capacity

    assert capacity(320 * 240) == (24_000, 40_000) and capacity(100 * 80) == (24_000, 40_000)
    assert capacity(640 * 480) == (48_000, 56_000) and capacity(360 * 640) == (42_000, 48_000)
    ds = load_dataset(synth)
    tr = Trainer(ds, tmp_path / "a", tiny_config(init_points=0, max_gaussians=0))
    assert (tr.cfg.init_points, tr.cfg.max_gaussians) == capacity(W * H)
    assert tr.dcfg.max_gaussians == tr.cfg.max_gaussians
    tr = Trainer(ds, tmp_path / "b", tiny_config(init_points=500, max_gaussians=0))
    assert (tr.cfg.init_points, tr.cfg.max_gaussians) == (500, 40_000)  # an explicit value is kept


def test_coarse_to_fine_is_on_by_default_only_for_photo_sized_images(synth, tmp_path):
    from splattwin.splat.trainer import auto_downscales

    assert auto_downscales(480) == 2 and auto_downscales(1080) == 2  # 640x480: 1/4 and 1/2 size first
    assert auto_downscales(360) == 1 and auto_downscales(300) == 1  # 360x640 photos: 1/2 size first
    assert auto_downscales(299) == 0 and auto_downscales(240) == 0  # 320x240: never
    cfg = tiny_config()
    assert cfg.num_downscales == -1  # the default: decided from the image size
    tr = Trainer(load_dataset(synth), tmp_path / "a", cfg)
    assert tr.cfg.num_downscales == 0 and len(tr.levels) == 1


def test_appearance_and_learnt_background_checkpoint_and_resume(synth, tmp_path):
    """Per-view colour corrections and an environment map are trained, written to extras.safetensors,
    checkpointed with the rest, and a killed run resumes to the same result."""
    from splattwin.splat import checkpoint as ckpt_io
    from splattwin.splat.eval import evaluate
    from splattwin.splat.extras import EXTRAS_FILE, read_background

    ds = load_dataset(synth)
    cfg = tiny_config(iters=40, checkpoint_every=20, appearance="affine", appearance_lr=5e-3,
                      background_mode="env", env_size=4, bg_sphere_points=50)
    a = train(ds, tmp_path / "a", cfg)
    assert len(a.gaussians) > 0
    st = ckpt_io.load(tmp_path / "a" / EXTRAS_FILE)
    A = st["appearance"]["A"].numpy()
    assert st["appearance"]["names"] == [f.name for f in ds.train()] and A.shape == (len(ds.train()), 3, 3)
    assert 0 < np.abs(A - np.eye(3)).max() < 0.5  # learnt, and near identity
    bg = read_background(tmp_path / "a")
    assert bg is not None and bg.mode == "env" and tuple(bg.param.shape) == (3, 4, 8)

    b = interrupted_then_resumed(ds, tmp_path / "b", cfg, at_step=27)
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    st_b = ckpt_io.load(tmp_path / "b" / EXTRAS_FILE)
    torch.testing.assert_close(st_b["appearance"]["A"], st["appearance"]["A"], rtol=0, atol=0)
    torch.testing.assert_close(st_b["background"]["param"], st["background"]["param"], rtol=0, atol=0)
    # evaluation composites the saved background: differs from rendering over black
    with_bg = evaluate(tmp_path / "a", ds, None, progress=False)
    over_black = evaluate(a.gaussians, ds, None, progress=False)
    assert with_bg.mean_psnr != over_black.mean_psnr
    assert np.isfinite(with_bg.mean_psnr_right_corrected)
    # a checkpoint of a run without these parts is not resumed by one with them (options differ)
    from splattwin.splat.trainer import CheckpointMismatch
    with pytest.raises(CheckpointMismatch):
        train(ds, tmp_path / "b", tiny_config(iters=40, checkpoint_every=20), resume=True)


def test_background_sphere_adds_initial_gaussians(synth, tmp_path):
    ds = load_dataset(synth)
    plain = Trainer(ds, tmp_path / "p", tiny_config(iters=1, bg_sphere_points=0))
    plain._fresh_state()
    sph = Trainer(ds, tmp_path / "s", tiny_config(iters=1, bg_sphere_points=300, bg_sphere_radius=4.0))
    sph._fresh_state()
    assert len(sph.model) == len(plain.model) + 300
    r = np.linalg.norm(sph.model.params["means"].detach().numpy()[-300:] - sph.scene_center, axis=1)
    np.testing.assert_allclose(r, r[0], rtol=1e-5)
    assert r[0] >= 4.0 * sph.scene_scale - 1e-6


def test_inverse_depth_mode_trains(scene_small, tmp_path):
    """The inverse-depth loss pulls rendered depth towards the measurement like the relative one."""
    from splattwin.splat.trainer import depth_loss, load_views

    ds = load_dataset(scene_small)
    views = load_views(ds.train(), 2, depth=True)
    cfg = tiny_config(iters=120, resolution=2, sh_degree=0, init="random", init_points=2000, densify=False)
    err = {}
    for lam in (0.0, 0.5):
        tr = Trainer(ds, tmp_path / str(lam), TrainConfig(**{**cfg.__dict__, "depth_lambda": lam,
                                                             "depth_mode": "inverse"}))
        tr.run()
        with torch.no_grad():
            err[lam] = np.mean([float(depth_loss(img[..., 3], a[..., 0], v.depth, "relative"))
                                for v, (img, a, _) in ((v, tr.render(i, render_mode="RGB+ED"))
                                                       for i, v in enumerate(views))])
    assert err[0.5] < 0.6 * err[0.0], err


def test_learnt_environment_uses_the_coarse_level_camera(synth, tmp_path):
    """At a coarse level the environment map is looked up through that level's intrinsics (the image is
    smaller); the full-size K would look up directions outside the picture."""
    import splattwin.splat.extras as X

    ds = load_dataset(make_dataset(tmp_path / "big", width=128, height=96))
    seen = []
    real = X.apply

    def spy(app, bg, img, alpha, idx, K, *a, **k):
        seen.append((tuple(img.shape[:2]), float(K[0, 2])))
        return real(app, bg, img, alpha, idx, K, *a, **k)

    X.apply = spy
    try:
        train(ds, tmp_path / "o", tiny_config(iters=8, num_downscales=1, downscale_every=0.5,
                                              background_mode="env", env_size=4))
    finally:
        X.apply = real
    for (h, w), cx in seen:
        assert abs(cx - w / 2) < 0.3 * w, (h, w, cx)   # the principal point of the image drawn
    assert {hw for hw, _ in seen} == {(48, 64), (96, 128)}


def test_first_and_later_training_in_a_process_agree(synth, tmp_path):
    # The first numba parallel call in a process resets torch's thread count to OpenMP's; torch.sigmoid
    # rounds differently at its 2-thread chunk boundary (> 32768 elements), so the first training in a
    # process (left on 2 torch threads) differed from a later one (1 thread): bench/train.py --repeat and
    # resumed builds saw different Gaussians. A fresh interpreter, so the first run really is the first.
    import os
    import subprocess
    import sys

    import splattwin

    code = (
        "import json, tempfile, numpy as np, torch, splattwin.runtime as r; r.configure(numba_threads=2)\n"
        "from pathlib import Path\n"
        "from splattwin.capture import load_dataset\n"
        "from splattwin.splat.trainer import TrainConfig, Trainer\n"
        "torch.set_num_threads(2)\n"
        f"ds = load_dataset(Path({str(synth)!r}))\n"
        "cfg = TrainConfig(iters=6, checkpoint_every=0, progress=False, resolution=1, sh_degree=0, backend='cpu')\n"
        "seen, g = [], []\n"
        "for _ in range(2):\n"
        "    s = set()\n"
        "    g.append(Trainer(ds, Path(tempfile.mkdtemp()), cfg).run(callback=lambda i: s.add(torch.get_num_threads())).gaussians)\n"
        "    seen.append(sorted(s))\n"
        "print(json.dumps({'seen': seen, 'after': torch.get_num_threads(), 'equal': all(bool(np.array_equal("
        "getattr(g[0], k), getattr(g[1], k))) for k in ('means', 'scales', 'opacities', 'sh'))}))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(splattwin.__file__).resolve().parents[1]))
    env.pop("OMP_WAIT_POLICY", None)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"seen": [[1], [1]], "after": 2, "equal": True}


def test_sparse_profile_resolves_only_automatic_values():
    from splattwin.splat.config import SPARSE_DENSIFY_GRAD, SPARSE_DROP_RATE, SPARSE_SH_DEGREE, SPARSE_SPHERE_POINTS

    cap = 48_000
    cfg, line = TrainConfig(max_gaussians=cap).resolved(7)
    assert SPARSE_SH_DEGREE < 3 and 0 < SPARSE_DROP_RATE < 1
    assert (cfg.sh_degree, cfg.bg_sphere_points, cfg.densify_grad, cfg.drop_rate) == (
        SPARSE_SH_DEGREE, SPARSE_SPHERE_POINTS, SPARSE_DENSIFY_GRAD, SPARSE_DROP_RATE)
    assert cfg.densify_config().grad_threshold == SPARSE_DENSIFY_GRAD and "7 training views" in line
    assert f"drop_rate {SPARSE_DROP_RATE:g}" in line
    dense, line = TrainConfig(max_gaussians=cap).resolved(15)
    assert (dense.sh_degree, dense.bg_sphere_points, dense.densify_config().grad_threshold) == (3, 0, 2e-4)
    assert dense.drop_rate == 0 and line == ""
    # what the user set stays; --sparse-views 0 turns the profile off
    mine, _ = TrainConfig(max_gaussians=cap, sh_degree=2, bg_sphere_points=0, densify_grad=3e-4,
                          drop_rate=0.0).resolved(7)
    assert (mine.sh_degree, mine.bg_sphere_points, mine.densify_config().grad_threshold) == (2, 0, 3e-4)
    assert mine.drop_rate == 0
    off, line = TrainConfig(max_gaussians=cap, sparse_views=0).resolved(3)
    assert (off.sh_degree, off.bg_sphere_points, off.drop_rate) == (3, 0, 0) and line == ""
    # the sphere never takes more than a tenth of a small cap
    assert TrainConfig(max_gaussians=2000).resolved(5)[0].bg_sphere_points == 200


def test_sparse_capture_trains_with_the_profile(synth, tmp_path):
    """8 training views (< 10): SH degree 1, the background sphere, the sparse threshold, DropGaussian; all
    recorded."""
    import json

    from splattwin.splat.config import SPARSE_DROP_RATE

    cfg = TrainConfig(iters=40, checkpoint_every=0, progress=False, backend="cpu", max_gaussians=2000)
    res = train(load_dataset(synth), tmp_path / "out", cfg)
    info = json.loads((tmp_path / "out" / "train.json").read_text())
    assert info["profile"].startswith("sparse capture (8 training views")
    assert info["config"]["sh_degree"] == 1 and info["config"]["bg_sphere_points"] == 200
    assert info["config"]["densify_cfg"]["grad_threshold"] == 6e-4
    assert info["config"]["drop_rate"] == SPARSE_DROP_RATE
    assert res.gaussians.sh_degree == 1
    dense = TrainConfig(iters=40, checkpoint_every=0, progress=False, backend="cpu", max_gaussians=2000,
                        sparse_views=0)
    train(load_dataset(synth), tmp_path / "dense", dense)
    info = json.loads((tmp_path / "dense" / "train.json").read_text())
    assert info["profile"] == "dense (defaults)" and info["config"]["sh_degree"] == 3


def test_training_renders_with_the_configs_low_pass(synth, tmp_path):
    """The trainer's renders use `TrainConfig.filter_eps2d()`: antialiased with eps2d 0 (auto) is
    Mip-Splatting's 0.1, an explicit eps2d as given; an out-of-range eps2d is refused up front."""
    from splattwin.errors import InputError

    ds = load_dataset(synth)

    def render_with(**kw):
        t = Trainer(ds, tmp_path / f"t{len(kw)}{kw.get('eps2d', 0)}", tiny_config(iters=10, **kw))
        t._fresh_state()
        with torch.no_grad():
            img = t.render(0, sh_degree=0)[0]
            act = t.model.activated()
            v = t.levels[0][0]
            ref = {eps: rasterization(act["means"], act["quats"], act["scales"], act["opacities"], act["sh"],
                                      t.viewmats[0:1], t.Ks_levels[0][0:1], v.camera.width, v.camera.height,
                                      sh_degree=0, backgrounds=t.bg, backend=t.backend,
                                      rasterize_mode=t.cfg.rasterize_mode, eps2d=eps)[0][0] for eps in (0.1, 0.2, 0.3)}
        return img, ref

    img, ref = render_with(rasterize_mode="antialiased")
    torch.testing.assert_close(img, ref[0.1])
    assert (img - ref[0.3]).abs().max() > 1e-3  # the low-pass matters on these splats: the test can fail
    img, ref = render_with(rasterize_mode="antialiased", eps2d=0.2)
    torch.testing.assert_close(img, ref[0.2])
    img, ref = render_with()
    torch.testing.assert_close(img, ref[0.3])
    with pytest.raises(InputError, match="eps2d"):
        Trainer(ds, tmp_path / "bad", tiny_config(eps2d=-1.0))


@pytest.mark.parametrize("resolution", [1, 2])
def test_load_views_undistorts_photos_to_the_rasterizers_pinhole(tmp_path, resolution):
    """A photo with lens distortion is trained on (and evaluated against) as its ideal pinhole image: the
    loaded view's camera has no distortion and its pixels match a pinhole render of the scene; the photo
    as taken, compared with a pinhole render at its own intrinsics (what training did before), does not."""
    import dataclasses

    from splattwin.capture.undistort import distort_image, pinhole_for
    from splattwin.errors import InputError
    from splattwin.splat.losses import psnr_from_mse
    from splattwin.splat.trainer import load_views

    g = gt_gaussians()
    cam = dataclasses.replace(ring_cameras(1, 160, 120)[0], dist=np.array([0.12, 0.02, 0.0, 0.0]), name="d0")
    pin = pinhole_for(cam)
    fine = pin.scaled(2.0)
    photo = distort_image(render_gaussians(g, fine), fine, cam)
    p = write_image(tmp_path / "d0.png", (np.clip(photo, 0, 1) * 255 + 0.5).astype(np.uint8))
    view = load_views([Frame(image_path=p, camera=cam)], resolution)[0]
    assert view.camera.dist is None
    expect = pin.scaled(1.0 / resolution)
    np.testing.assert_allclose(view.camera.K, expect.K, rtol=1e-9)
    truth = render_gaussians(g, expect)
    inner = (slice(2, -2), slice(2, -2))
    psnr = lambda a, b: float(psnr_from_mse(torch.tensor(float(np.mean((a[inner] - b[inner]) ** 2)))))  # noqa: E731
    ok = psnr(view.image.numpy(), truth)
    raw = load_views([Frame(image_path=p, camera=dataclasses.replace(cam, dist=None))], resolution)[0]
    naive = psnr(raw.image.numpy(), render_gaussians(g, raw.camera))
    assert ok > 40.0 and ok > naive + 10.0, (ok, naive)
    bad = dataclasses.replace(cam, dist=np.array([-8.0, 0.0, 0.0, 0.0]))  # folds back: no lens does that
    with pytest.raises(InputError, match=r"d0\.png.*cannot be undistorted"):
        load_views([Frame(image_path=p, camera=bad)], resolution)


def _nan_means(sd):
    sd["model"]["params"]["means"][0, 0] = float("nan")


def _fewer_means(sd):
    sd["model"]["params"]["means"] = sd["model"]["params"]["means"][:3]


@pytest.mark.parametrize("edit, needle", [
    (_nan_means, "NaN"),                          # resumed into an all-NaN point_cloud.ply, exit 0
    (lambda sd: sd.update(step=10**15), "step"),  # "resumed a finished run at step 10**15"
    (lambda sd: sd.update(step=-5), "step"),      # sh_degree -1: internal error
    (lambda sd: sd.update(order=[10**6]), "order"),
    (lambda sd: sd.update(order=[-1]), "order"),
    (_fewer_means, "shape"),
    (lambda sd: sd.update(history=[{"step": "x"}]), "history"),
])
def test_resume_refuses_an_inconsistent_checkpoint_naming_it(synth, tmp_path, edit, needle):
    from splattwin.errors import InputError
    from splattwin.splat import checkpoint

    ds = load_dataset(synth)
    cfg = tiny_config(iters=4, checkpoint_every=2)
    train(ds, tmp_path / "a", cfg)
    ck = sorted((tmp_path / "a" / "checkpoints").glob("*.safetensors"))[-1]
    sd = checkpoint.load(ck)
    edit(sd)
    checkpoint.save(ck, sd)
    with pytest.raises(InputError, match=needle) as e:
        train(ds, tmp_path / "a", cfg, resume=True)
    assert e.value.path == ck


def test_appearance_auto_follows_the_poses_exposure_check(synth, tmp_path):
    """--appearance auto trains a per-image gain when the poses report beside the dataset says the photos'
    exposures differ, and records the decision in train.json; without the report: off. The default (off)
    trains without one and records the suggestion."""
    import json
    import shutil

    from splattwin.splat import checkpoint as ckpt_io
    from splattwin.splat.extras import EXTRAS_FILE

    shutil.copytree(synth, tmp_path / "d")
    assert tiny_config().appearance == "off"
    cfg = tiny_config(iters=10, appearance="auto")
    train(load_dataset(tmp_path / "d"), tmp_path / "plain", cfg)
    rec = json.loads((tmp_path / "plain" / "train.json").read_text())["appearance"]
    assert rec["mode"] == "off" and rec["decision"] == "none"
    ex = tmp_path / "plain" / EXTRAS_FILE
    assert not ex.is_file() or ckpt_io.load(ex)["appearance"] is None
    (tmp_path / "d" / "poses_report.json").write_text(json.dumps({"exposure": {
        "varies": True, "spread_pct": 30.0, "threshold_pct": 10.0, "images_off": ["view_000"]}}))
    train(load_dataset(tmp_path / "d"), tmp_path / "auto", cfg)
    tj = json.loads((tmp_path / "auto" / "train.json").read_text())
    assert tj["appearance"]["mode"] == "gain" and tj["appearance"]["decision"] == "auto"
    assert tj["config"]["appearance"] == "gain"
    st = ckpt_io.load(tmp_path / "auto" / EXTRAS_FILE)
    assert st["appearance"]["mode"] == "gain"
    train(load_dataset(tmp_path / "d"), tmp_path / "default", tiny_config(iters=10))
    rec = json.loads((tmp_path / "default" / "train.json").read_text())["appearance"]
    assert rec["mode"] == "off" and rec["decision"] == "suggested" and rec["images_off"] == ["view_000"]


# -- the colour corrections start at the poses stage's measured gains (appearance.initial_gains) ------------
GAINS = {"train_000": [0.72, 0.70, 0.78], "train_001": [0.85, 0.88, 0.80], "train_002": [0.95, 1.0, 0.92],
         "train_003": [1.0, 1.0, 1.0], "train_004": [1.0, 0.97, 1.05], "train_005": [1.12, 1.05, 1.2],
         "train_006": [1.2, 1.25, 1.15], "train_007": [1.3, 1.26, 1.34]}


def _with_exposure(synth: Path, root: Path, record: dict | None, gains: dict | None = None) -> Path:
    """A copy of `synth` whose training photos are scaled by `gains` (8-bit, clipped; held-out ones as
    rendered) and, unless record is None, a poses_report.json beside it with that "exposure" record."""
    import shutil

    from splattwin.capture import load_image

    shutil.copytree(synth, root)
    for name, g in (gains or {}).items():
        p = root / "images" / f"{name}.png"
        write_image(p, np.round(np.clip(load_image(p) * np.asarray(g), 0, 1) * 255).astype(np.uint8))
    if record is not None:
        (root / "poses_report.json").write_text(json.dumps({"exposure": record}))
    return root


def _measured(gains: dict) -> dict:
    return {"varies": True, "spread_pct": 34.0, "threshold_pct": 10.0, "images_off": list(gains),
            "images": {n: {"gain": float(np.exp(np.log(g).mean())), "rgb_gain": g, "samples": 100}
                       for n, g in gains.items()}}


def test_appearance_corrections_start_at_the_measured_gains(synth, tmp_path):
    """At step 0 each training view's correction is diag(its measured rgb_gain) with no bias, in gain and
    affine mode; a view the record lacks starts at 1; train.json records where the start came from."""
    gains = {n: g for n, g in GAINS.items() if n != "train_005"}
    ds = load_dataset(_with_exposure(synth, tmp_path / "d", _measured(gains)))
    for mode in ("gain", "affine"):
        t = Trainer(ds, tmp_path / mode, tiny_config(iters=1, appearance=mode))
        t._fresh_state()
        A, b = t.appearance.as_arrays()
        names = [v.name for v in t.views]
        want = np.stack([np.diag(gains.get(n, [1.0, 1.0, 1.0])) for n in names])
        np.testing.assert_allclose(A, want, atol=1e-6)
        np.testing.assert_array_equal(b, 0.0)
        assert float(t.appearance.regularizer(names.index("train_000")).detach()) == 0.0   # centred on the measurement
        rec = t.appearance_record
        assert rec["init"] == "measured" and rec["init_views"] == 7 and "train_005" in rec["init_why"]
    train(ds, tmp_path / "run", tiny_config(iters=2, appearance="auto"))
    tj = json.loads((tmp_path / "run" / "train.json").read_text())["appearance"]
    assert tj["mode"] == "gain" and tj["init"] == "measured" and tj["init_views"] == 7
    # the learnt corrections' common part, from the saved corrections (absent when none is trained)
    from splattwin.splat import checkpoint as ckpt_io

    saved = ckpt_io.load(tmp_path / "run" / "extras.safetensors")["appearance"]
    A, b = saved["A"].numpy(), saved["b"].numpy()
    np.testing.assert_allclose(tj["gauge"]["gain"], np.exp(np.log(np.diagonal(A, axis1=1, axis2=2)).mean(0)),
                               atol=1e-4)
    np.testing.assert_allclose(tj["gauge"]["bias"], b.mean(0), atol=1e-4)
    train(ds, tmp_path / "off", tiny_config(iters=2, appearance="off"))
    assert "gauge" not in json.loads((tmp_path / "off" / "train.json").read_text())["appearance"]


def test_measured_gains_are_the_right_direction(synth, tmp_path):
    """Photos rendered with known per-view gains, their gains measured by the poses stage's exposure check
    (`poses.exposure.measure_exposure`, the record the splat stage reads; within ~5 % on this 48x36 scene),
    a few training steps: the corrections stay near the applied gains (model colour -> photo, relative to
    the median photo), not at 1 nor at their inverse."""
    from splattwin.poses.exposure import measure_exposure

    root = _with_exposure(synth, tmp_path / "d", None, GAINS)
    ds = load_dataset(root)
    rec = measure_exposure([f.camera for f in ds.frames], [f.image_path for f in ds.frames],
                           [f.name for f in ds.frames], ds.points_xyz)
    assert "error" not in rec, rec
    (root / "poses_report.json").write_text(json.dumps({"exposure": rec}))
    ds = load_dataset(root)
    t = Trainer(ds, tmp_path / "run", tiny_config(iters=40, appearance="gain"))
    res = t.run()
    A, _ = t.appearance.as_arrays()
    got = np.stack([np.diag(a) for a in A])
    # the record is relative to the median image over all photos (held-out ones: as rendered, gain 1)
    log_all = np.log([GAINS.get(f.name, [1.0, 1.0, 1.0]) for f in ds.frames])
    want = np.exp(np.log([GAINS[v.name] for v in t.views]) - np.median(log_all, axis=0))
    assert np.abs(want - 1).max() > 0.25           # identity (or the inverse) would be far off
    np.testing.assert_allclose(got, want, atol=0.06)
    assert res.steps == 40


def test_appearance_corrections_start_at_one_without_a_usable_measurement(synth, tmp_path, caplog):
    """A malformed exposure record (or none): the corrections start at 1, said in the log and train.json."""
    bad = {**_measured(GAINS), "varies": "yes"}
    ds = load_dataset(_with_exposure(synth, tmp_path / "d", bad))
    with caplog.at_level("INFO", logger="splattwin.splat.appearance"):
        t = Trainer(ds, tmp_path / "run", tiny_config(iters=1, appearance="gain"))
        t._fresh_state()
    A, _ = t.appearance.as_arrays()
    np.testing.assert_array_equal(A, np.broadcast_to(np.eye(3), A.shape))
    assert t.appearance_record["init"] == "identity" and "no exposure check read" in t.appearance_record["init_why"]
    assert "malformed \"exposure\"" in caplog.text and "start at gain 1" in caplog.text


def test_training_leaves_the_callers_torch_random_state_alone(synth, tmp_path):
    """A run seeds torch's global generator with cfg.seed; it reseeded the caller's, so a notebook's next
    torch.rand after training changed (audit 10A L9). The caller's state is restored now."""
    torch.manual_seed(7)
    expected = torch.rand(4)
    torch.manual_seed(7)
    train(load_dataset(synth), tmp_path / "out", tiny_config(iters=3))
    assert torch.equal(torch.rand(4), expected)


def test_train_takes_a_dataset_path_as_evaluate_does(synth, tmp_path):
    """train("path/to/dataset", out) failed deep inside with "'str' object has no attribute 'meta'"
    (audit 10A L17); evaluate and fuse_to_dir already take a path."""
    from splattwin.errors import InputError

    res = train(str(synth), tmp_path / "out", tiny_config(iters=3))
    assert res.steps == 3 and (tmp_path / "out" / "point_cloud.ply").is_file()
    with pytest.raises(InputError, match="does not exist"):
        train(tmp_path / "no_dataset", tmp_path / "out2", tiny_config(iters=3))
