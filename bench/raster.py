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

from splattwin.splat.rasterize import rasterization  # noqa: E402

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


KERNELS = [  # (name in splattwin.splat._cpu / its kernels module, what it does)
    ("project_fwd", "EWA projection"), ("sh_fwd", "SH colours"), ("make_records", "records + opacity-aware boxes"),
    ("depth_order", "depth sort (numpy SIMD)"), ("bin_tiles", "tile binning + packing"),
    ("raster_fwd", "compositing forward"), ("raster_bwd", "compositing backward"),
    ("reduce_isect_grads", "per-Gaussian gradient sums"), ("sh_bwd", "SH backward"),
    ("project_bwd", "projection backward")]


def _pair_stats(packed, tile_start, width, height, last):
    """(pairs up to each tile's last contributor, rows with a non-empty span, lanes inside the spans)."""
    import numba
    import numpy as np

    from splattwin.splat._cpu import kernels as K_

    @numba.njit(cache=False)
    def stats(packed, tile_start, width, height, last):
        tw = (width + 15) // 16
        pairs, rows, lanes = 0, 0, 0
        buf = np.empty((6, 16), np.float32)
        IA, IB, EF, EL, CF, DY = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5]
        for t in range(len(tile_start) - 1):
            tx0, ty0 = (t % tw) * 16, (t // tw) * 16
            tx1, ty1 = min(tx0 + 16, width) - 1, min(ty0 + 16, height) - 1
            kmax = last[ty0:ty1 + 1, tx0:tx1 + 1].max()
            for k in range(tile_start[t], tile_start[t] + kmax + 1):
                u, v = np.float64(packed[k, K_.R_U]), np.float64(packed[k, K_.R_V])
                ca, cb, cc = packed[k, K_.R_A], packed[k, K_.R_B], packed[k, K_.R_C]
                level, lop = np.float64(packed[k, K_.R_LEVEL]), np.float64(packed[k, K_.R_LOP])
                b_a, hdet_a, ha, inv_ha = K_._pair_consts(ca, cb, cc)
                bx0, bx1 = max(np.int64(packed[k, K_.R_X0]), tx0) - tx0, min(np.int64(packed[k, K_.R_X1]), tx1) - tx0
                ry0, ry1 = max(np.int64(packed[k, K_.R_Y0]), ty0) - ty0, min(np.int64(packed[k, K_.R_Y1]), ty1) - ty0
                K_._rows(v, ty0, ry0, ry1, u - (tx0 + 0.5), b_a, hdet_a, inv_ha, level, lop, bx0, bx1, 16, IA, IB, EF,
                         EL, CF, DY)
                pairs += 1
                for r in range(16):
                    if IA[r] <= IB[r]:
                        rows += 1
                        lanes += int(IB[r] - IA[r]) + 1
        return pairs, rows, lanes

    return stats(packed, tile_start, width, height, last)


def profile_cpu(scene, W: int, H: int, N: int, repeats: int) -> dict:
    """Per-kernel wall and CPU time (medians over `repeats` fwd+bwd runs after a warm-up) and the work they
    do: Gaussians drawn, (tile, Gaussian) pairs, tile list lengths, rows and lanes composited, bytes of the
    main arrays each pass streams."""
    import numpy as np

    from splattwin.splat import _cpu
    from splattwin.splat._cpu import kernels as K_

    params, K = scene(W, H, N)
    weights = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(1))
    times: dict[str, list] = {name: [] for name, _ in KERNELS}
    cap: dict = {}
    saved = {}
    for name, _ in KERNELS:
        mod = _cpu if name == "depth_order" else K_
        f = saved[name] = (mod, getattr(mod, name))

        def timed(*a, _f=f[1], _name=name):
            t0, c0 = time.perf_counter(), time.process_time()
            r = _f(*a)
            times[_name].append((time.perf_counter() - t0, time.process_time() - c0))
            if _name in ("raster_fwd", "bin_tiles"):
                cap[_name] = a
            return r
        setattr(mod, name, timed)
    try:
        totals = []
        for rep in range(repeats + 1):
            if rep == 1:
                for v in times.values():
                    v.clear()
                totals.clear()
            tf, tb, tc, _ = run_once("cpu", params, K, W, H, weights)
            totals.append((tf + tb, tc))
    finally:
        for name, (mod, f) in saved.items():
            setattr(mod, name, f)
    med = lambda xs: statistics.median(xs) * 1e3  # noqa: E731
    out = {"kernels": {n: (med([t[0] for t in times[n]]), med([t[1] for t in times[n]])) for n, _ in KERNELS},
           "total": (statistics.median(t[0] for t in totals), statistics.median(t[1] for t in totals))}
    packed, tile_start, _, _, _, _, _, last = cap["raster_fwd"]
    order = cap["bin_tiles"][0]
    lens = np.diff(tile_start)
    pairs, rows, lanes = _pair_stats(packed, tile_start, W, H, last)
    M, D = packed.shape[0], packed.shape[1] - K_.R_COL
    out["stats"] = {
        "drawn": int(order.shape[0]), "pairs": int(M), "tiles_per_gaussian": M / max(1, order.shape[0]),
        "list_mean": float(lens.mean()), "list_median": float(np.median(lens)), "list_max": int(lens.max()),
        "pairs_before_stop": pairs / max(1, M), "rows_per_pair": rows / max(1, pairs),
        "lanes_per_row": lanes / max(1, rows), "span_pixels_per_pixel": lanes / (W * H),
        "packed_mb": packed.nbytes / 2**20, "pair_grad_mb": M * (6 + D) * 4 / 2**20,
        "sh_mb": N * 16 * 3 * 4 / 2**20}
    return out


def print_profile(profiles: dict) -> None:
    """Where the time goes: one column per size, kernels as rows, then the work statistics."""
    keys = list(profiles)
    print(f"\nwhere the time goes (CPU backend, fwd+bwd; wall / CPU ms, medians):")
    print(f"  {'kernel':<20} {'what':<30}" + "".join(f" {k:>20}" for k in keys))
    for name, what in KERNELS:
        cells = "".join(f" {profiles[k]['kernels'][name][0]:>9.1f} / {profiles[k]['kernels'][name][1]:>7.1f}" for k in keys)
        print(f"  {name:<20} {what:<30}{cells}")
    cells = "".join(f" {profiles[k]['total'][0]:>9.1f} / {profiles[k]['total'][1]:>7.1f}" for k in keys)
    print(f"  {'total':<20} {'(incl. Python/torch glue)':<30}{cells}")
    rows = [("Gaussians drawn", "drawn", "{:.0f}"), ("(tile, Gaussian) pairs", "pairs", "{:.0f}"),
            ("tiles per Gaussian", "tiles_per_gaussian", "{:.2f}"),
            ("tile list length mean / median / max", None, None),
            ("pairs before the tile's early stop", "pairs_before_stop", "{:.1%}"),
            ("rows per pair", "rows_per_pair", "{:.2f}"), ("span lanes per row", "lanes_per_row", "{:.2f}"),
            ("span pixels per image pixel", "span_pixels_per_pixel", "{:.1f}"),
            ("packed records MB (1 write, 2 reads)", "packed_mb", "{:.1f}"),
            ("pair gradients MB (1 write, 1 read)", "pair_grad_mb", "{:.1f}"),
            ("SH coefficients MB (3 passes)", "sh_mb", "{:.1f}")]
    for label, key, fmt in rows:
        if key is None:
            cells = "".join(f" {'%.0f / %.0f / %d' % (profiles[k]['stats']['list_mean'], profiles[k]['stats']['list_median'], profiles[k]['stats']['list_max']):>20}"
                            for k in keys)
        else:
            cells = "".join(f" {fmt.format(profiles[k]['stats'][key]):>20}" for k in keys)
        print(f"  {label:<51}{cells}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--skip-reference", action="store_true")
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: available cores)")
    ap.add_argument("--png", default=None, help="save CPU | reference | 10x difference at 160x120/20k here")
    ap.add_argument("--no-profile", action="store_true", help="skip the per-kernel breakdown")
    args = ap.parse_args()
    import numba

    if args.threads:
        numba.set_num_threads(args.threads)
    torch.set_num_threads(numba.get_num_threads())
    rows, out = [], {"threads": numba.get_num_threads()}
    imgs = {}
    runs = [("surface", make_surface_scene, W, H, N) for W, H, N in SIZES]
    runs.append(("volume", make_volume_scene, 320, 240, 50_000))
    from splattwin.progress import track

    for name, scene, W, H, N in track(runs, "cpu backend", unit="size"):
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
    if not args.no_profile:
        profiles = {}
        for W, H, N in SIZES[1:]:
            key = f"{W}x{H}_{N // 1000}k"
            profiles[key] = profile_cpu(make_surface_scene, W, H, N, args.repeats)
            out[f"profile_cpu_ms_{key}"] = {n: round(v[1], 2) for n, v in profiles[key]["kernels"].items()}
        print_profile(profiles)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
