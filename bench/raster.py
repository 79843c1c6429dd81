"""Benchmark of the Gaussian rasterizer: CPU backend (numba) forward/backward and the dense PyTorch reference.

Why a CPU rasterizer of our own: no differentiable CPU Gaussian rasterizer exists on PyPI (gsplat and
taichi-splatting are GPU-only; gsplat's "torch" path still calls CUDA kernels), and a dense all-pairs
PyTorch version is O(H W N) in time and memory (tens of seconds per step at 160x120/20k). Users without a
GPU, and all our tests, need a fast one: `splattwin.splat._cpu` (numba, tile-based, hand-written backward).

Scenes (see `make_surface_scene`, `make_volume_scene`): "surface" is tabletop-like (flat Gaussians on a table
and four spheres, seen from 1 m, as a trained scene), "volume" a dense fog of ~80 overlapping Gaussians per
pixel (stress case, 320x240/50k only). Pinhole camera, horizontal FOV 56 deg, SH degree 3 (as at the end of
training). Loss = sum(image * random weights), gradients to every parameter.

Prints a table (median of --repeats timed runs after a warm-up) and, as the last line, a JSON object.
Usage: python bench/raster.py [--repeats 5] [--skip-reference] [--threads N]
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from splattwin.splat.rasterization import rasterization  # noqa: E402

SIZES = [(160, 120, 20_000), (320, 240, 50_000), (640, 480, 200_000)]


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _camera(W: int, H: int):
    f = 0.5 * W / math.tan(0.5 * math.radians(56))
    return torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]])


def make_surface_scene(W: int, H: int, N: int, seed: int = 0, coverage: float = 8.0):
    """Tabletop-like scene: flat Gaussians on a 1.2 x 0.9 m table plane and four spheres (r 0.06-0.12 m),
    seen from 1 m at 45 deg. Tangential scales log-uniform in [0.5, 2] x sigma0 with
    N pi (2 sigma0)^2 = coverage x surface area; normal scale 0.1 x tangential; opacities 0.3-1."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor([[0.1, 0.1, 0.12], [-0.2, 0.05, 0.08], [0.15, -0.2, 0.06], [-0.1, -0.15, 0.1]])
    radii = centres[:, 2].clone()
    areas = torch.cat([torch.tensor([1.2 * 0.9]), 4 * math.pi * radii ** 2])
    which = torch.multinomial(areas / areas.sum(), N, replacement=True, generator=g)
    pts = torch.empty(N, 3)
    nrm = torch.empty(N, 3)
    plane = which == 0
    n0 = int(plane.sum())
    pts[plane] = torch.stack([(torch.rand(n0, generator=g) - 0.5) * 1.2, (torch.rand(n0, generator=g) - 0.5) * 0.9,
                              torch.zeros(n0)], 1)
    nrm[plane] = torch.tensor([0.0, 0.0, 1.0])
    d = torch.randn(N - n0, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    sph = which[~plane] - 1
    pts[~plane] = centres[sph] + radii[sph, None] * d
    nrm[~plane] = d
    # rotation taking e_z to the normal, then a random spin about it
    q = torch.stack([1 + nrm[:, 2], -nrm[:, 1], nrm[:, 0], torch.zeros(N)], 1)
    q[nrm[:, 2] < -0.999] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    q = q / q.norm(dim=1, keepdim=True)
    phi = torch.rand(N, generator=g) * math.pi
    quats = _quat_mul(q, torch.stack([torch.cos(phi), torch.zeros(N), torch.zeros(N), torch.sin(phi)], 1))
    sigma0 = math.sqrt(coverage * float(areas.sum()) / (4 * math.pi * N))
    st = sigma0 * torch.exp(torch.empty(N, 2).uniform_(math.log(0.5), math.log(2.0), generator=g))
    scales = torch.cat([st, 0.1 * st.min(dim=1, keepdim=True).values], 1)
    opac = 0.3 + 0.7 * torch.rand(N, generator=g)
    sh = torch.randn(N, 16, 3, generator=g) * 0.1
    sh[:, 0] = torch.randn(N, 3, generator=g) * 0.5
    # camera 1 m from the table centre, 45 deg elevation, looking at the origin (OpenCV: y down)
    from splattwin.capture.camera import look_at
    T_world_cam = look_at([-0.7, 0.0, 0.7], [0.0, 0.0, 0.05])
    vm = torch.tensor(_invert(T_world_cam), dtype=torch.float32)[None]
    return [pts, quats, scales, opac, sh, vm], _camera(W, H)


def _invert(T):
    import numpy as np
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def make_volume_scene(W: int, H: int, N: int, seed: int = 0):
    """Stress case: N Gaussians uniformly in a 2 x 1.5 x 2 m box 2-4 m in front of the camera, random
    rotations, scales log-uniform in [0.005, 0.03] m x sqrt(50k / N), opacities 0.1-0.9 (a fog of ~80
    overlapping Gaussians per pixel; far denser than a trained scene)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(N, 3, generator=g) * torch.tensor([2.0, 1.5, 2.0]) + torch.tensor([-1.0, -0.75, 2.0])
    quats = torch.randn(N, 4, generator=g)
    s = math.sqrt(50_000 / N)
    scales = torch.exp(torch.empty(N, 3).uniform_(math.log(0.005), math.log(0.03), generator=g)) * s
    opac = 0.1 + 0.8 * torch.rand(N, generator=g)
    sh = torch.randn(N, 16, 3, generator=g) * 0.1
    sh[:, 0] = torch.randn(N, 3, generator=g) * 0.5
    return [means, quats, scales, opac, sh, torch.eye(4)[None]], _camera(W, H)


def run_once(backend, params, K, W, H, weights):
    xs = [p.detach().clone().requires_grad_(True) for p in params]
    t0, c0 = time.perf_counter(), time.process_time()
    img, alpha, meta = rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], K, W, H, sh_degree=3,
                                     backend=backend)
    t1, c1 = time.perf_counter(), time.process_time()
    (img * weights).sum().backward()
    t2, c2 = time.perf_counter(), time.process_time()
    return (t1 - t0) * 1e3, (t2 - t1) * 1e3, (c2 - c0) * 1e3, img.detach()


def bench(backend, scene, W, H, N, repeats):
    params, K = scene(W, H, N)
    weights = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(1))
    if backend != "reference":
        run_once(backend, params, K, W, H, weights)  # warm-up (numba compile / cache load)
    f, b, c = [], [], []
    img = None
    for _ in range(repeats):
        tf, tb, tc, img = run_once(backend, params, K, W, H, weights)
        f.append(tf)
        b.append(tb)
        c.append(tc)
    return statistics.median(f), statistics.median(b), statistics.median(c), img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--skip-reference", action="store_true")
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: available cores)")
    ap.add_argument("--png", default=None, help="save CPU | reference | 10x difference at 160x120/20k here")
    args = ap.parse_args()
    import numba

    from splattwin.splat import _cpu  # noqa: F401  (sets the numba thread count)
    if args.threads:
        numba.set_num_threads(args.threads)
    torch.set_num_threads(numba.get_num_threads())
    rows, out = [], {"threads": numba.get_num_threads()}
    imgs = {}
    runs = [("surface", make_surface_scene, W, H, N) for W, H, N in SIZES]
    runs.append(("volume", make_volume_scene, 320, 240, 50_000))
    from tqdm import tqdm

    for name, scene, W, H, N in tqdm(runs, desc="cpu backend", unit="size"):
        tf, tb, tc, img = bench("cpu", scene, W, H, N, args.repeats)
        imgs[(name, W, H, N)] = img
        key = f"{W}x{H}_{N // 1000}k" + ("" if name == "surface" else f"_{name}")
        out[f"fwd_ms_{key}"] = round(tf, 2)
        out[f"bwd_ms_{key}"] = round(tb, 2)
        out[f"fwd_bwd_ms_{key}"] = round(tf + tb, 2)
        out[f"fwd_bwd_cpu_time_ms_{key}"] = round(tc, 2)
        rows.append(("cpu", name, key, tf, tb, tc))
    if not args.skip_reference:
        W, H, N = SIZES[0]
        print(f"dense reference at {W}x{H}/{N // 1000}k (slow: one run) ...", flush=True)
        tf, tb, tc, img = bench("reference", make_surface_scene, W, H, N, 1)
        if args.png:
            from splattwin.io import write_image
            cpu = imgs[("surface", W, H, N)][0]
            diff = (10 * (img[0] - cpu).abs()).clamp(0, 1)
            panel = torch.cat([cpu.clamp(0, 1), img[0].clamp(0, 1), diff], dim=1)
            write_image(args.png, (panel.numpy() * 255).round().astype("uint8"))
        key = f"{W}x{H}_{N // 1000}k"
        out[f"reference_fwd_ms_{key}"] = round(tf, 1)
        out[f"reference_bwd_ms_{key}"] = round(tb, 1)
        out["speedup_vs_reference"] = round((tf + tb) / out[f"fwd_bwd_ms_{key}"], 1)
        out["max_abs_diff_vs_reference"] = float((img - imgs[("surface", W, H, N)]).abs().max())
        rows.append(("reference (dense torch)", "surface", key, tf, tb, tc))
    print(f"{'backend':<24} {'scene':<8} {'size':<22} {'fwd ms':>9} {'bwd ms':>9} {'fwd+bwd':>9} {'cpu-time':>9}")
    for name, scene, key, tf, tb, tc in rows:
        print(f"{name:<24} {scene:<8} {key:<22} {tf:>9.1f} {tb:>9.1f} {tf + tb:>9.1f} {tc:>9.1f}")
    print(f"(wall-clock medians of {args.repeats} runs after a warm-up, {out['threads']} threads; reference: 1 run; "
          f"cpu-time = process CPU time summed over threads; SH degree 3)")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
