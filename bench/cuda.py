"""Benchmark and check of the "cuda" backend (gsplat's CUDA kernels behind `rasterization()`) on a real GPU.

    python bench/cuda.py [--repeats 5] [--sizes 640x480x200000,1920x1080x500000] [--train DATASET --iters 3000]

Our tests run the "cuda" backend through gsplat's Python front end with CPU emulations of its kernels
(tests/splat/conftest.py); this script is the check on the real kernels, run where a GPU is present:

1. Parity (`parity`): the tabletop-like scene of bench/raster.py (`make_surface_scene`), small, rendered by
   the "cuda" backend, our "cpu" backend and the float64 "reference", with gradients of a random-weighted
   loss to every input. Two regimes: opacities <= 0.35, where gsplat's opacity-aware extent and our
   3-sigma box admit the same pixels and neither alpha clamp (gsplat 0.999, ours 0.99) is reached, so
   the backends must agree to float32 rounding; and opacities 0.3-1 (a trained scene's), where they differ
   by gsplat's own small choices (reported, not judged). Rows: max |image diff|, max |alpha diff|, and
   per input the relative gradient error ||g - g_ref|| / ||g_ref||.
2. Speed (`speed`): forward and forward+backward milliseconds, median of --repeats after a warm-up, CUDA
   synchronised, "cuda" beside "cpu" (this machine's cores) in the same run.
3. Training (`train`, with --train): `splattwin train DATASET --device cuda --iters N`, then `eval` on its
   held-out views: PSNR / SSIM, seconds; with --refine-poses also a run that learns the camera poses (the
   one-camera renders whose pose gradients `cuda_backend` makes exact).

Last line: one JSON object (`parity_ok`, the parity figures, the speed table, the training figures).
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from splattwin.splat.rasterize import rasterization  # noqa: E402

_spec = importlib.util.spec_from_file_location("_bench_raster", Path(__file__).with_name("raster.py"))
raster = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(raster)

NAMES = ["means", "quats", "scales", "opacities", "sh", "viewmats"]
# float32 kernels against the float64 reference, in the regime where the backends' rules coincide: the
# CPU backend's own agreement (tests/splat/test_raster.py) is ~1e-6 on images and ~1e-4 on gradients
PARITY_TOL_IMG = 1e-4
PARITY_TOL_GRAD = 1e-3


def _sync():
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _render(backend, params, K, W, H, weights, dtype=torch.float32):
    xs = [p.detach().to(dtype).clone().requires_grad_(True) for p in params]
    img, alpha, _ = rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], K.to(dtype), W, H, sh_degree=3,
                                  backend=backend)
    loss = (img * weights.to(img.device, img.dtype)).sum() + (alpha * weights[..., :1].to(img.device, img.dtype)).sum()
    loss.backward()
    return img.detach().cpu().double(), alpha.detach().cpu().double(), {n: x.grad.double() for n, x in zip(NAMES, xs)}


def parity(W=96, H=72, N=1500, seed=0) -> dict:
    out = {}
    for regime, cap in (("opacity<=0.35", 0.35), ("opacity 0.3-1", None)):
        params, K = raster.make_surface_scene(W, H, N, seed=seed)
        if cap is not None:
            params[3] = 0.05 + (cap - 0.05) * torch.rand(N, generator=torch.Generator().manual_seed(seed + 1))
        weights = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(seed + 2))
        ref = _render("reference", params, K, W, H, weights, dtype=torch.float64)
        row = {}
        for backend in ("cuda", "cpu"):
            img, alpha, grads = _render(backend, params, K, W, H, weights)
            row[backend] = {
                "img_max_abs": float((img - ref[0]).abs().max()),
                "img_mean_abs": float((img - ref[0]).abs().mean()),
                "alpha_max_abs": float((alpha - ref[1]).abs().max()),
                "grad_rel": {n: float((grads[n] - ref[2][n]).norm() / ref[2][n].norm().clamp_min(1e-30))
                             for n in NAMES}}
        out[regime] = row
    return out


def _time(backend, params, K, W, H, weights, repeats):
    fwd, both = [], []
    for i in range(repeats + 1):
        xs = [p.detach().clone().requires_grad_(True) for p in params]
        _sync()
        t0 = time.perf_counter()
        img, _, _ = rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], K, W, H, sh_degree=3, backend=backend)
        _sync()
        t1 = time.perf_counter()
        (img * weights.to(img.device)).sum().backward()
        _sync()
        t2 = time.perf_counter()
        if i:  # the first is the warm-up (numba compile / cache load, CUDA context and kernel load)
            fwd.append((t1 - t0) * 1e3)
            both.append((t2 - t0) * 1e3)
    return statistics.median(fwd), statistics.median(both)


def speed(sizes, repeats) -> list[dict]:
    rows = []
    for W, H, N in sizes:
        params, K = raster.make_surface_scene(W, H, N)
        weights = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(1))
        row = {"size": f"{W}x{H}", "gaussians": N}
        for backend in ("cuda", "cpu"):
            f, fb = _time(backend, params, K, W, H, weights, repeats)
            row[f"{backend}_fwd_ms"], row[f"{backend}_fwd_bwd_ms"] = round(f, 2), round(fb, 2)
        row["speedup_fwd_bwd"] = round(row["cpu_fwd_bwd_ms"] / row["cuda_fwd_bwd_ms"], 1)
        rows.append(row)
    return rows


def train(dataset: str, iters: int, out: Path, extra: list[str] = ()) -> dict:
    cli = [sys.executable, "-c", "import sys; from splattwin.cli import main; sys.exit(main(sys.argv[1:]))"]
    t0 = time.perf_counter()
    rc = subprocess.call(cli + ["train", dataset, str(out), "--device", "cuda", "--iters", str(iters), "--no-progress",
                                *extra])
    t_train = time.perf_counter() - t0
    if rc != 0:
        return {"rc": rc}
    rc = subprocess.call(cli + ["eval", str(out), "--dataset", dataset, "--device", "cuda", "--no-progress"])
    m = json.loads((out / "eval" / "metrics.json").read_text()) if rc == 0 else {}
    tj = json.loads((out / "train.json").read_text())
    return {"rc": rc, "iters": iters, "options": " ".join(extra), "train_s": round(t_train, 1), "psnr": m.get("mean_psnr"),
            "ssim": m.get("mean_ssim"), "gaussians": tj.get("gaussians"),
            "backend": tj.get("backend"), "mean_psnr_as_given": m.get("mean_psnr_as_given")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sizes", default="320x240x50000,640x480x200000,1920x1080x500000")
    ap.add_argument("--train", metavar="DATASET", help="also train and evaluate on DATASET with --device cuda")
    ap.add_argument("--iters", type=int, default=3000)
    ap.add_argument("--refine-poses", action="store_true", help="also train with --refine-poses (exact pose gradients)")
    ap.add_argument("--out", default="/tmp/splattwin_cuda_bench", help="training output folder")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("bench/cuda.py needs a CUDA GPU (torch.cuda.is_available() is False)")
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name()}, gsplat "
          f"{__import__('gsplat').__version__}", flush=True)
    t0 = time.perf_counter()
    _render("cuda", *raster.make_surface_scene(32, 24, 10)[0:2], 32, 24, torch.ones(1, 24, 32, 3))
    print(f"first cuda call (gsplat's kernels built or loaded): {time.perf_counter() - t0:.1f} s", flush=True)

    par = parity()
    print(f"\n{'regime':16} {'backend':7} {'img max':>9} {'img mean':>9} {'alpha max':>9}  grad rel: "
          + " ".join(f"{n:>9}" for n in NAMES))
    for regime, row in par.items():
        for backend, r in row.items():
            print(f"{regime:16} {backend:7} {r['img_max_abs']:9.2e} {r['img_mean_abs']:9.2e} {r['alpha_max_abs']:9.2e}"
                  f"             " + " ".join(f"{r['grad_rel'][n]:9.2e}" for n in NAMES))
    exact = par["opacity<=0.35"]["cuda"]
    parity_ok = exact["img_max_abs"] < PARITY_TOL_IMG and exact["alpha_max_abs"] < PARITY_TOL_IMG and \
        max(exact["grad_rel"].values()) < PARITY_TOL_GRAD
    print(f"parity (opacities <= 0.35, cuda vs float64 reference): {'ok' if parity_ok else 'FAILED'}", flush=True)

    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    sp = speed(sizes, args.repeats)
    print(f"\n{'size':>10} {'N':>8} {'cuda fwd':>9} {'cuda f+b':>9} {'cpu fwd':>9} {'cpu f+b':>9} {'x':>6}  (ms, median of "
          f"{args.repeats}; cpu: {torch.get_num_threads()} threads)")
    for r in sp:
        print(f"{r['size']:>10} {r['gaussians']:8d} {r['cuda_fwd_ms']:9.2f} {r['cuda_fwd_bwd_ms']:9.2f} "
              f"{r['cpu_fwd_ms']:9.2f} {r['cpu_fwd_bwd_ms']:9.2f} {r['speedup_fwd_bwd']:6.1f}", flush=True)

    tr = None
    if args.train:
        tr = [train(args.train, args.iters, Path(args.out) / "plain")]
        if args.refine_poses:
            tr.append(train(args.train, args.iters, Path(args.out) / "refine_poses", ["--refine-poses"]))
        for t in tr:
            print(f"\ntrain --device cuda: {t}", flush=True)
    print(json.dumps({"parity_ok": parity_ok, "parity": par, "speed": sp, "train": tr,
                      "torch": torch.__version__, "device": torch.cuda.get_device_name()}))


if __name__ == "__main__":
    main()
