"""Options of the splat stage (`train`, `splattwin train`, `build --splat.*`): `TrainConfig` and its
`LearningRates`, the single source of their defaults and help (see `splattwin.options`).

Light on purpose: no torch here, so `splattwin --help` builds the training flags without importing it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

from splattwin.options import option

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.splat.densify import DensifyConfig

# the rasterizer's default low-pass per mode (px^2); kept here, torch-free, and re-exported by
# `splat.rasterize` (see there for why)
DEFAULT_EPS2D = {"classic": 0.3, "antialiased": 0.1}
LEGACY_EPS2D = 0.3  # what every config trained with before it recorded eps2d, in both modes
MAX_EPS2D = 10.0
DEVICES = ("auto", "cpu", "cuda")
INIT_METHODS = ("auto", "sfm", "depth", "triangulate", "random")
APPEARANCE_MODES = ("off", "gain", "affine", "auto")   # splat/appearance.py
BACKGROUND_MODES = ("fixed", "color", "env")      # splat/background.py
DEPTH_MODES = ("relative", "inverse")             # splat/depth_loss.py
# the sparse-view profile (`TrainConfig.resolved`)
SPARSE_SH_DEGREE = 1
SPARSE_SPHERE_POINTS = 3000
SPARSE_DENSIFY_GRAD = 6e-4                          # dense captures keep DensifyConfig's 3DGS default
SPARSE_DROP_RATE = 0.5                              # DropGaussian's final rate; dense captures: off


@dataclass
class LearningRates:
    """Adam learning rates (3DGS/gsplat defaults). `means` is multiplied by the scene scale and decays
    exponentially to `means_final_factor` times its start over the run."""

    means: float = option(1.6e-4, "Adam LR of the means (times the scene scale)")
    means_final_factor: float = option(0.01, "the means' LR decays exponentially to this times its start")
    scales: float = option(5e-3, "Adam LR of the log scales")
    quats: float = option(1e-3, "Adam LR of the rotations")
    opacities: float = option(5e-2, "Adam LR of the opacity logits")
    sh0: float = option(2.5e-3, "Adam LR of the DC colour")
    shN: float = option(2.5e-3 / 20, "Adam LR of the higher SH bands")


@dataclass
class TrainConfig:
    """Training options. Defaults suit sparse tabletop captures (~15 views, 320x240) on a CPU.

    resolution: as 3DGS `-r`: 1, 2, 4, 8 divide the image size; a larger value is a target width in
        pixels; -1 downsizes only images wider than 1600 px; 0 (auto, default): on the CPU the longest
        side is capped at `cpu_max_side` (640 px), with CUDA full size (`splattwin.splat.resolution`).
    eval_full_resolution: held-out views are evaluated at the training resolution unless this is set.
    refine_poses / pose_lr / pose_start: joint per-camera SE(3) corrections, their Adam LR, and the
        fraction of the run before they move. Start 0 and LR 5e-3 measured best (bench/train.py, cameras
        off by 1.5 deg / 2.3 cm: left 0.34 deg / 0.41 cm, vs 1.43 deg / 2.1 cm with start 0.2, LR 1e-3).
    init_points / max_gaussians: at most this many initial Gaussians / Gaussians at any time; 0 (the
        default): 24k / 28k for 320x240 training images, times sqrt(pixels / (320 x 240)) for larger ones,
        the cap at least 40k (`splattwin.splat.resolution.capacity`: 40k at 320x240, 48k at 360x640, 56k at
        640x480). Embedded scene at 320x240 (bench/train.py, 3000 steps, held-out dB): cap 28k 32.82, 36k
        32.96, 40k 33.02, 44k 32.98 (scene seed 1: 34.19 with 28k, 34.31 with 36k); 40k costs ~12 % more
        CPU time per run and passes 32.9 dB by step 2000. Larger images did not take the same step up: at
        640x480, 80k gave 34.26 dB against 33.78 with 56k, but the statue photos (7 views at 360x640) fell
        from 14.40 dB held-out with 48k to 13.10 with 69k, so only the floor moved. Earlier: 20k / 26k
        32.48 dB at 320x240; at 640x480 a 28k cap left 32.53 dB / 0.958.
    rasterize_mode: "classic" or "antialiased" (see `rasterization`); evaluation renders with the same
        mode (train.json), and so does the playback (`DynamicScene.rasterize_mode`, from twin.json).
        Antialiased measured no better on a 2x2-sampled scene (SSIM 0.919 vs 0.921), but on the demo's
        5x5-sampled scene (seed 0, 3000 steps) held-out 34.10 dB / SSIM 0.956 vs 32.01 / 0.948 classic,
        and the twin after the robot's task (bench/photoreal.py) 28.51 vs 27.79 dB: the demo trains with it.
    eps2d: the low-pass added to each projected Gaussian's covariance (px^2; 0: `DEFAULT_EPS2D` of the mode).
        Antialiased with 3DGS's 0.3 (the value before this option) blurs every Gaussian wider than the pixel
        it is seen through; 0.1 (Mip-Splatting's) matches a pixel's box filter (demo scene, 3000 steps,
        held-out 34.10 -> 36.31 dB / SSIM 0.956 -> 0.974). On real photos (statue, 3000 steps, default
        hold-out) antialiased 0.3 -> 0.1: 15.98 -> 16.32 dB (SSIM 0.463 -> 0.465), the build's classic
        16.37 / 0.474, classic with 0.1 16.43 / 0.469 (seed noise ~0.1 dB): the build keeps classic and
        0.3. Recorded with the config; a config without it (older twins) was trained with 0.3
        (`trained_filter`).
    opacity_reg: weight of a mean-opacity penalty (gsplat's opacity_reg; 0: off). 0.05 raised held-out
        SSIM by ~0.006-0.009 (4x4-sampled scene: 0.956 vs 0.949; 2x2-sampled: 0.930 vs 0.921), but the
        fainter Gaussians overlap more (~58 instead of ~50 composited per pixel): ~15-25 % slower.
    drop_rate: DropGaussian, a structural regulariser for sparse views: at step t of T a share
        drop_rate * t / T of the Gaussians, drawn afresh each step (its own generator, checkpointed), is
        left out of the training render and the rest drawn at opacity / (1 - share), so no Gaussian can
        explain a view on its own. Evaluation and every later stage render all Gaussians at their opacity.
        On by default only on sparse captures (figures in `resolved`).
    depth_lambda: weight of a depth loss on frames that have depth maps (0: off, also when the capture has
        depth): `depth_mode` "relative" |ED - D| / D or "inverse" |1/ED - 1/D| of the rendered expected
        depth ED over pixels with a measured depth D (holes: 0/NaN/inf, never pulled) and rendered alpha >
        0.5 (`splattwin.splat.depth_loss`). Off by default: it helps with perfect depth but not with
        D435-like depth. bench/depth.py (the robot-style capture, 16 views at 320x240, every 4th held out,
        1500 steps, medians of seeds 0 and 1; its `DepthNoise`: median error 3.7 mm, ~5 % of the surface
        pixels lost): without depth loss held-out 31.56 dB / SSIM 0.934, rendered depth median |ED -
        D_true| 62 mm, object-surface F1@5mm of the Gaussian centres 0.425. With D435-like depth, every
        weight costs PSNR and none lifts the F1: inverse 0.01 / 0.05 / 0.2: 31.35 / 31.28 / 30.98 dB,
        4.0 / 2.4 / 2.1 mm, F1 0.411 / 0.400 / 0.392; relative 0.01 / 0.05 / 0.2: 31.10 / 30.87 / 30.39
        dB, 3.9 / 2.8 / 2.6 mm, F1 0.41-0.40. With perfect depth, weight 0.2 helps everywhere: relative
        31.84 dB, 1.3 mm, F1 0.462 (inverse 31.71 dB, 1.3 mm, 0.462). Whole builds (mesh F1@5mm against
        the scene's meshes, mean over the usable objects): seed 0 off 0.834, inverse 0.01 0.828, inverse
        0.05 0.950; seed 1 off 0.862, inverse 0.05 0.855. Turn it on (inverse, 0.05) where the rendered
        depth matters more than colour (depth renders, compositing) or where the depth is clean.
    robust_quantile / robust_start: transient masks (`splattwin.splat.robust`, after RobustNeRF): from
        robust_start of the run, each step leaves out of its photo's loss the blobs of pixels whose residual
        is above the robust_quantile of that photo's and 4x its median -- what that photo alone shows. Off
        by default; the final masks are drawn in OUT/transients.png and their shares recorded in train.json.
        bench/transients.py (the embedded scene, 15 views at 320x240, three random opaque "passers-by"
        painted into each training photo, clean held-out photos, 3000 steps, seeds 0/1): held-out 29.67 dB
        / SSIM 0.934 without masks, 31.82 / 0.946 with quantile 0.8 (clean capture 33.10 / 0.954); 94 % of
        the painted pixels and 1.8 % of the others masked in the last pass. On the real photo collection
        (british_museum: 8 training views from 8 cameras, people in the held-out photos as well) 11.65 ->
        11.63 dB, SSIM 0.528 -> 0.536 (a first version, the quantile interpolated: 11.54; start 0: 11.44):
        with so few views the model fits a crowd close to one camera with floaters before its residual
        stands out, so photo collections do not get the masks automatically.
    num_downscales / downscale_every: coarse-to-fine schedule (as nerfstudio's splatfacto and OpenSplat):
        the first steps render 1/2^num_downscales of the training size, and the size doubles every
        downscale_every * iters steps (0 or 0.0: always the training size; see
        `splattwin.splat.trainer.resolution_level`). -1 (the default): `auto_downscales` - none below 300 px
        on the short side, else as many halvings (at most 2) as keep the coarsest level >= 120 px.
        Measured with 5 % of the steps per level (3000 steps): embedded scene at 640x480 (56k Gaussians)
        33.78 dB / SSIM 0.968 with 2 levels vs 33.69 / 0.970 without, ~8 % less work; statue photos
        (7 training views at 360x640, 48k; an earlier hold-out, not the default ends 000/016) 18.8 dB
        held-out with 1 level vs 17.7 without; but at 320x240 any coarse phase cost 0.1-0.2 dB (1 level:
        32.72 vs 32.85 dB; 2 levels: 32.69; 2 levels of 10 %:
        32.36).
    densify_cfg: the adaptive density control schedule (None: `DensifyConfig.for_iterations`); set from
        Python only.
    """

    iters: int = option(3000, "training steps", build_alias="iters")
    resolution: int = option(0, "0 (auto): longest side capped at --cpu-max-side on the CPU, full size with CUDA; "
                             "1/2/4/8 divide the image size, larger values are a target width in px, -1 caps "
                             "the width at 1600", build_alias="resolution")
    cpu_max_side: int = option(640, "--resolution 0 (auto) on the CPU: images whose longest side is larger are "
                               "trained at this size", unit="px", build_alias="cpu-max-side")
    eval_full_resolution: bool = option(False, "evaluate the held-out views at the full image size (default: at "
                                        "the training resolution)", build_alias="eval-full-resolution")
    device: str = option("auto", "rasterizer device: cuda uses gsplat", choices=DEVICES, build_alias="device")
    backend: str | None = option(None, "rasterizer backend by name (e.g. reference), overriding --device")
    init: str = option("auto", "initial point cloud: dataset/SfM points, back-projected depth maps, points "
                       "triangulated from the known poses, or random in the cameras' common view (auto: the first "
                       "available in that order)", choices=INIT_METHODS)
    init_stereo: int = option(0, "add up to this many points from plane-sweep stereo on the training views to "
                              "the SfM/triangulated ones (0: off; see TrainConfig.resolved for what it gave on "
                              "the real photos)", build_alias="init-stereo")
    init_points: int = option(0, "at most this many initial Gaussians (0: 24000 for 320x240 images, scaled "
                              "with the square root of the pixel count above)")
    sh_degree: int = option(-1, "maximum SH degree (-1: auto: 3, or 1 on a sparse capture, see --sparse-views)",
                            choices=(-1, 0, 1, 2, 3))
    sh_interval: int = option(0, "raise the SH degree every this many steps (0: iters // 10)")
    seed: int = option(0, "seed of the view order, initialisation and split samples")
    checkpoint_every: int = option(500, "steps between checkpoints (0: none)", hashed=False)
    refine_poses: bool = option(False, "learn a per-camera SE(3) pose correction jointly (writes "
                                "refined_poses.json)")
    pose_lr: float = option(5e-3, "Adam learning rate of the pose corrections")
    pose_start: float = option(0.0, "fraction of the run before the poses start to move")
    ssim_lambda: float = option(0.2, "weight of D-SSIM in the photometric loss (1 - l) L1 + l D-SSIM")
    rasterize_mode: str = option("classic", "rasterizer mode (evaluation renders with the same)",
                                 choices=("classic", "antialiased"))
    eps2d: float = option(0.0, "the rasterizer's low-pass filter, px^2 at the training size (0: auto by mode: 0.3 "
                          "classic, 3DGS's dilation; 0.1 antialiased, Mip-Splatting's 2D filter, about one pixel's "
                          "box filter); evaluation and the playback render with the same")
    depth_lambda: float = option(0.0, "weight of a depth loss on frames with depth maps (0: off; on D435-like "
                                 "depth, inverse 0.05 cut the rendered-depth error 62 -> 2.4 mm but cost 0.3 dB "
                                 "held-out PSNR, bench/depth.py)")
    depth_mode: str = option("relative", "depth loss: relative |ED-D|/D, or inverse-depth L1 |1/ED-1/D| (1/m); "
                             "pixels without measured depth are masked", choices=DEPTH_MODES)
    appearance: str = option("off", "per-image colour correction learnt with the splats: per-channel gain+bias, "
                             "or affine 3x3+bias (held-out views: identity); auto: gain when the poses stage's "
                             "exposure check found the photos' gains differ (poses_report.json), else off. Off "
                             "by default: on photos that differ a warning suggests it (bench/exposure.py, corrections "
                             "started at the measured gains: +1.03 and -0.53 dB against the unperturbed photos on "
                             "two seeds at 500 steps)", choices=APPEARANCE_MODES)
    appearance_lr: float = option(1e-3, "Adam learning rate of the colour corrections")
    appearance_reg: float = option(0.01, "weight of the corrections' squared distance from where they start (the "
                                   "poses stage's measured per-image gains, else identity)")
    background_mode: str = option("fixed", "what shows behind the splats: the fixed --background colour, a learnt "
                                  "colour, or a learnt environment map (far field by ray direction)",
                                  choices=BACKGROUND_MODES)
    background_lr: float = option(1e-2, "Adam learning rate of the learnt background")
    env_size: int = option(16, "environment map height in texels (width: twice)")
    bg_sphere_points: int = option(-1, "extra initial Gaussians on a sphere around the scene, coloured from the "
                                   "training images (-1: auto: 3000 on a sparse capture, else 0; 0: off)")
    bg_sphere_radius: float = option(3.0, "background sphere radius in scene scales (at least beyond 98 % of "
                                     "the initial points)")
    opacity_reg: float = option(0.0, "weight of a mean-opacity penalty, as gsplat's opacity_reg (0: off; 0.05 "
                                "gave +0.27 dB / +0.009 SSIM on the embedded scene, ~15 % slower)")
    drop_rate: float = option(-1.0, "DropGaussian: each training step hides a random fraction of the Gaussians, "
                              "ramped linearly from 0 to this rate over the run (the others' opacities "
                              "scaled by 1/(1-fraction)), so no Gaussian can fit a view alone (-1: auto: "
                              f"{SPARSE_DROP_RATE:g} on a sparse capture, else 0; 0: off)")
    robust_quantile: float = option(0.0, "transient masks: pixels whose residual is above this quantile of their "
                                    "photo's (and 4x its median), where they form blobs, are left out of that photo's "
                                    "loss: people, cars or banners seen in one photo only (0: off; 0.8 suggested; "
                                    "`splattwin.splat.robust`)")
    robust_start: float = option(0.2, "fraction of the run before the transient masks start (the static scene is "
                                 "fitted first)")
    densify_grad: float = option(0.0, "densification's threshold on a Gaussian's mean view-space gradient "
                                 "(0: auto: 2e-4 as 3DGS, 6e-4 on a sparse capture)")
    sparse_views: int = option(10, "a capture with fewer training views than this is sparse: --sh-degree, "
                               "--bg-sphere-points, --densify-grad and --drop-rate left on auto become 1, 3000, "
                               "6e-4 and 0.5 (0: never)")
    max_gaussians: int = option(0, "cap on the Gaussian count (0: 28000 x sqrt(pixels / 320x240), "
                                "at least 40000)")
    background: tuple[float, float, float] = option((0.0, 0.0, 0.0), "background colour (RGB in [0, 1])")
    densify: bool = option(True, "adaptive density control (clone, split, prune)")
    lrs: LearningRates = option(factory=LearningRates, help="Adam learning rates")
    densify_cfg: DensifyConfig | None = option(None, "densification schedule (None: scaled to iters)", cli=False)
    num_downscales: int = option(-1, "coarse-to-fine: start at 1/2^N of the training size (0: off; -1: auto, "
                                 "none below 300 px on the short side, else up to 2 halvings keeping >= 120 px)")
    downscale_every: float = option(0.05, "coarse-to-fine: fraction of the steps spent at each coarse level")
    progress: bool = option(True, "progress bar", runtime=True)

    def densify_config(self) -> DensifyConfig:
        from splattwin.splat.densify import DensifyConfig

        if self.densify_cfg is not None:
            return self.densify_cfg
        d = DensifyConfig.for_iterations(self.iters, self.max_gaussians)
        return replace(d, grad_threshold=self.densify_grad) if self.densify_grad > 0 else d

    def resolved(self, n_views: int) -> tuple[TrainConfig, str]:
        """This config with the sparse-view profile's automatic values filled in for `n_views` training
        views, and a line saying what was chosen ('' when the capture is not sparse). Call it once
        max_gaussians is known (the sphere takes at most a tenth of it).

        Sparse profile (n_views < sparse_views): SH degree 1, a 3000-Gaussian background sphere, a 3x
        higher densification threshold and DropGaussian at rate 0.5. With few views the higher SH bands and
        the many small Gaussians that densification grows fit each photo's own view (the held-out views see
        streaks and floaters), and the far field, seen by few views, is best started as geometry. Statue
        photos (7 training views of 9 at 360x640, held out 000 and 016; held-out dB after 1500 / 3000
        steps): dense defaults 14.67 / 14.46, SH 0 15.12 / 14.77, + sphere + learnt environment map
        15.38 / 15.29 (at 2500), + threshold 6e-4 15.66 / 15.49, without the environment map 15.75 / 15.52,
        the same with SH degree 1
        (the profile) 15.67 / 15.65 (SSIM 0.456). Tried and left out: a 10k sphere 15.32 at 2000,
        an anisotropy penalty (0.01, r 10) 14.58 at 1500, threshold 1e-3 15.85, cap 24k 15.88 / 15.61,
        antialiased rasterization 15.67 at 1500 (these with SH 0), opacity_reg 0.05 14.08 at 2000, a longer
        coarse phase 15.62 at 2000, --refine-poses 14.70 at 1000. Left opt-in: plane-sweep stereo points
        (`--init-stereo 10000`, splat/mvs.py; 3000 steps, paired seeds, bench/real.py --sections
        stereo_init): statue 15.39 -> 15.76 dB, SSIM 0.451 -> 0.470 over 3 seeds (each +0.11 to +0.57;
        another SfM run of the same photos +0.16 / +0.07), +53 s on 2 cores; but the cake (7 views around
        it, one held-out view) 10.81 / 9.13 / 11.07 -> 10.73 / 10.50 / 10.84 dB with SSIM lower in all three
        seeds (-0.008 to -0.019). As depth supervision (the fused depth maps, depth_lambda 0.1) 15.37.
        DropGaussian (CVPR 2025; `drop_rate`: each step a random share of the Gaussians is hidden, ramped
        to the rate over the run, the rest drawn at opacity / (1 - share)) keeps single Gaussians from
        fitting one view alone; 3000 steps, seeds 0/1/2, held-out dB (SSIM mean): statue 15.65 / 15.72 /
        15.66 (0.452) -> rate 0.3 16.19 / 16.29 / 16.05 (0.472) -> rate 0.5 16.37 / 16.20 / 16.32 (0.471);
        cake 10.81 / 9.13 / 11.07 (0.378) -> 0.3 11.56 / 11.48 / 11.07 (0.450) -> 0.5 11.86 / 12.26 / 11.68
        (0.455); rate 0.7 (seed 0) 16.25 and 11.90. On the dense embedded scene (15 views, antialiased)
        rate 0.3 cost 0.19 dB and 0.018 SSIM (32.87 vs 33.06), so dense captures keep it off. Stereo points
        on top of it (seeds 0/1): statue 16.40 / 16.39, cake 10.72 / 10.18: still opt-in. Also measured on
        the statue with DropGaussian and undistorted photos (16.51 on seed 0), not kept: AbsGS densification
        (per-pixel |grad| sums, threshold 2.4e-3) 16.37 (training views 25.06 -> 27.27 dB: overfits), the
        position LR x2 16.77 / 16.44 / 16.58 (seeds 0/1/2) but the cake -1.6 dB (10.83 / 11.12 vs 12.48 /
        12.83), a log-depth smoothness loss in cameras between training cameras 16.44."""
        sparse = 0 < self.sparse_views and n_views < self.sparse_views
        auto = {"sh_degree": (self.sh_degree < 0, SPARSE_SH_DEGREE if sparse else 3),
                "bg_sphere_points": (self.bg_sphere_points < 0, min(SPARSE_SPHERE_POINTS, self.max_gaussians // 10)
                                     if sparse else 0),
                "densify_grad": (sparse and self.densify_grad <= 0, SPARSE_DENSIFY_GRAD),
                "drop_rate": (self.drop_rate < 0, SPARSE_DROP_RATE if sparse else 0.0)}
        chosen = {k: v for k, (is_auto, v) in auto.items() if is_auto}
        cfg = replace(self, **chosen)
        if not sparse or not chosen:
            return cfg, ""
        what = ", ".join(f"{k} {v:g}" for k, v in chosen.items())
        return cfg, (f"sparse capture ({n_views} training views < --sparse-views {self.sparse_views}): {what} "
                     f"(set them, or --sparse-views 0, to override)")

    def check(self) -> None:
        """InputError naming the first option out of its range (the trainer's check, and the build's
        pre-flight, so a bad value stops a build before pose estimation)."""
        from splattwin.errors import InputError

        if self.iters <= 0:
            raise InputError(f"--iters must be positive, got {self.iters}")
        if not -1 <= self.sh_degree <= 3:
            raise InputError(f"--sh-degree must be 0..3 (or -1: auto), got {self.sh_degree}")
        if not (self.drop_rate == -1 or 0 <= self.drop_rate < 1):
            raise InputError(f"--drop-rate must be in [0, 1) (or -1: auto), got {self.drop_rate:g}")
        if not (self.robust_quantile == 0 or 0.5 <= self.robust_quantile < 1):
            raise InputError(f"--robust-quantile must be in [0.5, 1) (or 0: off), got {self.robust_quantile:g}")
        if not 0.0 <= self.robust_start < 1.0:
            raise InputError(f"--robust-start must be in [0, 1), got {self.robust_start:g}")
        if not 0.0 <= self.eps2d <= MAX_EPS2D:
            raise InputError(f"--eps2d must be in [0, {MAX_EPS2D:g}] px^2 (0: auto), got {self.eps2d:g}")
        if self.device not in DEVICES:
            raise InputError(f"--device must be auto, cpu or cuda, got {self.device!r}")

    def filter_eps2d(self) -> float:
        """The low-pass this config trains with (px^2 at the training size): eps2d, or the mode's default."""
        return self.eps2d if self.eps2d > 0 else DEFAULT_EPS2D[self.rasterize_mode]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["densify_cfg"] = asdict(self.densify_config())
        return d


def filter_beside(ply) -> tuple[str, float]:
    """(rasterize_mode, eps2d) of the training run that wrote `ply` (the train.json in its folder, as
    `splattwin train` and the splat stage write it); ("classic", 0.3) for a PLY without one. InputError
    naming train.json when it cannot be read or holds a bad mode or low-pass."""
    from pathlib import Path

    from splattwin.errors import InputError
    from splattwin.io import read_json
    from splattwin.limits import MAX_RECORD_BYTES

    from splattwin.paths import own_file

    rec = own_file(Path(ply).parent, Path(ply).parent / "train.json", "train.json")
    if not rec.is_file():
        return trained_filter(None)
    info = read_json(rec, max_bytes=MAX_RECORD_BYTES)
    try:
        return trained_filter(info.get("config") if isinstance(info, dict) else None)
    except ValueError as e:
        raise InputError(f"config: {e}", rec) from None


def filter_for(trained: tuple[str, float | None], rasterize_mode: str | None = None) -> tuple[str, float | None]:
    """(mode, eps2d) to draw splats trained with `trained` = (mode, eps2d) in `rasterize_mode`: None or the
    trained mode keeps the trained low-pass; another mode takes its own default (eps2d None)."""
    return trained if rasterize_mode in (None, trained[0]) else (rasterize_mode, None)


def trained_filter(cfg: dict | None) -> tuple[str, float]:
    """(rasterize_mode, eps2d px^2) a recorded `TrainConfig.to_dict()` (train.json's config, twin.json's
    config.build.splat) was trained with: ("classic", 0.3) for none; a config without eps2d predates the
    option and used LEGACY_EPS2D. ValueError for an unknown mode or an eps2d outside [0, MAX_EPS2D]."""
    if not isinstance(cfg, dict):
        return "classic", DEFAULT_EPS2D["classic"]
    mode = cfg.get("rasterize_mode", "classic")
    if not isinstance(mode, str) or mode not in DEFAULT_EPS2D:  # (a list is unhashable: TypeError)
        raise ValueError(f"unknown rasterize_mode {mode!r} (one of {', '.join(DEFAULT_EPS2D)})")
    if "eps2d" not in cfg:
        return mode, LEGACY_EPS2D
    eps = cfg["eps2d"]
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0.0 <= eps <= MAX_EPS2D:
        raise ValueError(f"eps2d must be a number in [0, {MAX_EPS2D:g}] px^2, got {eps!r}")
    return mode, float(eps) if eps > 0 else DEFAULT_EPS2D[mode]
