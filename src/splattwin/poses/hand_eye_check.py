"""Do the robot poses + hand-eye fit the photos? Two tests on a few matched image pairs.

1. Inversion (rotations only). Robot poses give the end effector's motion between two images,
A = T_ee_a^-1 T_ee_b; the photos give the camera's, B = T_cam_a^-1 T_cam_b; a right hand-eye X = T_ee_cam
satisfies A X = X B, so the rotation R_B = R_X^T R_A R_X (the classic AX = XB hand-eye equation). Its inverse
X^-1 predicts R_X R_A R_X^T: the same rotation angle about another axis. A hand-eye that is mostly a turn about
the flange z axis plus a few centimetres keeps the optical axes where they were, so `robot.check_eye_in_hand`
cannot see the swap; the axes of the relative rotations can.

2. Pose consistency (rotation and translation, `consistency`). The Sampson (epipolar) error of each pair's
essential-matrix inliers under the relative pose the robot poses + hand-eye predict, in px at the matching
resolution (images at most MAX_SIDE px, so the full size of a 320x240 capture) and in mrad (px / focal
length). It is measured on near pairs (`neighbour_pairs`: each view with its nearest view in viewing
direction, as the splats combine them), where per-view pose errors show fully and a hand-eye error in
proportion to the pair's rotation. Measured on audit 8c's robot capture (320x240, f = 307 px): exact 0.06 px,
a good calibration (hand-eye 3 mm / 0.5 deg off) 0.27 px, latency (3 mm / 0.3 deg along the motion) 0.26 px,
focal length 2 % off 0.08 px, a poor calibration (10 mm / 2 deg) 1.11 px, per-view pose noise (3 mm / 0.3 deg
rms) 1.27 px; the last two lost ~4 dB of held-out PSNR and put objects 1.5-3 cm off. (Measured with the
keypoints a quarter pixel off the cameras' pixel convention; read in it (`_sift_points`, `_normalised_points`)
the embedded scene's 320x240 capture gives exact 0.087 px (0.096 before), good calibration 0.243 (0.219),
poor 0.859 (0.847), pose noise 1.064 (1.061): the verdicts are unchanged.) Verdict "warn" above
WARN_MRAD (0.49 px there), "bad" above BAD_MRAD (0.80 px), either only at >= FLOOR_FACTOR x the matches' own
error under their own essential matrix (blurred or badly textured photos match less precisely). "bad" with
`--poses.method auto` makes `estimate_poses` use SfM aligned to the robot poses instead; an explicit
`--poses.method robot` keeps the robot poses and warns.

3. Intrinsics (`intrinsics_check`) and latency (`latency_check`), on the matches of test 2 with the poses
held fixed: the focal-length scale and the principal point, and for poses matched to the images by timestamp
(TUM pose lists) the time offset between image and pose timestamps, that minimise the Sampson error
(truncated mean, a coarse-to-fine scan; the principal point with the focal scale again by Gauss-Newton from
a grid; bootstrap 1 sigma); a warning when they differ clearly from those in use (focal > 1.5 %, principal
point > 1 % of the focal length, offset > 15 ms). `check_poses_with_images` runs test 2 on known camera poses
(no hand-eye) for them.

The camera's relative rotations are measured

- from the photos (`--robot-poses` alone): SIFT + ratio test, essential matrix (RANSAC, the cameras'
  intrinsics and distortion) on at most MAX_IMAGE_PAIRS + MAX_CONSISTENCY_PAIRS image pairs at most
  MAX_SIDE px: a few seconds;
- from the SfM model (`--sfm` with robot poses): its cameras' rotations, free and more accurate (no pose
  consistency there: SfM's poses are used, the robot's only for the metric frame).

For test 1 only pairs where the two hypotheses predict rotations at least MIN_DISCRIMINATION_DEG apart are
used (a hand-eye turned by ~0 or 180 degrees about one axis is its own inverse in rotation: nothing to
decide), with a relative rotation of MIN..MAX_PAIR_ANGLE_DEG (overlap for matching; the ratio of noise to
signal).

Verdicts of test 1 (median rotation residual over the pairs, degrees):
- "inverted": the inverse fits clearly better (>= MIN_PAIRS pairs, the given one off by >= STRONG_DEG,
  the inverse at most a third of that, and better on >= 75 % of the pairs): the caller stops (InputError),
  since every camera pose, hence the twin and the real-arm files, would be wrong;
- "inverted?": the inverse fits better but on thin evidence: a warning;
- "mismatch": the given hand-eye is off by > MISMATCH_DEG and the inverse is no better: a warning. What it
  can see: gross errors only: a hand-eye rotation about 25 deg or more off, a focal length about x1.6 off, poses
  of other images. What it cannot see: realistic calibration errors (up to 20 deg of hand-eye rotation error
  stayed "consistent" in audit 8c), any translation error, per-view pose noise, timing errors: rotations
  alone are too weak for them; test 2 is the one that catches those;
- "consistent", or "undecided" (too few usable pairs), recorded in poses_report.json `hand_eye_check`
  (with test 2 under `pose_consistency`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

log = logging.getLogger(__name__)

MAX_IMAGE_PAIRS = 6          # image pairs matched when measuring from the photos
MAX_SFM_PAIRS = 60           # pairs read from an SfM model (no matching: cheap)
MAX_CANDIDATE_VIEWS = 80    # views among which the pairs are chosen
MAX_SIDE = 640               # px, longest image side for feature matching
MIN_PAIR_ANGLE_DEG = 5.0
MAX_PAIR_ANGLE_DEG = 45.0
MIN_DISCRIMINATION_DEG = 4.0  # the two hypotheses' predictions at least this far apart
MIN_INLIERS = 25
MIN_PAIRS = 3
STRONG_DEG = 5.0
MISMATCH_DEG = 10.0
# pose consistency (Sampson error of the matches under the robot-predicted relative poses)
MAX_CONSISTENCY_PAIRS = 8    # nearest-neighbour pairs matched for it
MIN_NEIGHBOUR_ANGLE_DEG = 2.0
WARN_MRAD = 1.6              # median Sampson error / focal: ~0.5 px at f = 307 px (320 x 240)
BAD_MRAD = 2.6               # ~0.8 px there: "clearly bad" (auto: SfM aligned to the robot poses instead)
FLOOR_FACTOR = 3.0           # and at least this many times the matches' own noise floor
# OpenCV's SIFT finds keypoints on the image upsampled 2x (pixel centres aligned) and scales them back by 0.5
# without the quarter-pixel that alignment shifts: its keypoints lie +0.25 px (both axes, every octave) off
# OpenCV's own convention (pixel centres at integers). Measured on Gaussian blobs at known centres, sigma
# 1.2-10 px (octaves -1..2): +0.25 px (tests/poses/test_robot.py).
SIFT_BIAS_PX = 0.25


@dataclass
class HandEyeCheck:
    verdict: str                      # consistent | inverted | inverted? | mismatch | undecided
    source: str                       # images | sfm
    pairs: list[dict] = field(default_factory=list)  # a, b, residual_deg, inverse_residual_deg[, inliers]
    residual_deg: float | None = None           # median over the pairs, the hand-eye as given
    inverse_residual_deg: float | None = None   # the same for its inverse
    consistency: dict | None = None   # `consistency()`: Sampson error under the robot-predicted poses (images)
    # the matched near pairs (i, j, PairMeasure) behind `consistency`, for the intrinsics / latency checks
    measures: list = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "source": self.source, "pairs": len(self.pairs),
                "residual_median_deg": self.residual_deg, "inverse_residual_median_deg": self.inverse_residual_deg,
                "per_pair": self.pairs, **({"pose_consistency": self.consistency} if self.consistency else {})}

    @property
    def poses_verdict(self) -> str | None:
        """ok | warn | bad from the pose consistency, None when not measured."""
        return None if not self.consistency else self.consistency.get("verdict")

    def describe(self) -> str:
        if self.residual_deg is None:
            return f"{len(self.pairs)} usable pair(s) from the {self.source}"
        return (f"relative camera rotations of {len(self.pairs)} {'image' if self.source == 'images' else 'SfM'} "
                f"pair(s) differ from those the robot poses predict by a median {self.residual_deg:.1f} deg with "
                f"the hand-eye as given, {self.inverse_residual_deg:.1f} deg with its inverse")


def rotation_angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def predicted_relative(T_ee_a: np.ndarray, T_ee_b: np.ndarray, R_ee_cam: np.ndarray) -> np.ndarray:
    """R_cam_a^T R_cam_b (camera b's orientation in camera a's frame) with R_base_cam = R_base_ee R_ee_cam."""
    return R_ee_cam.T @ (T_ee_a[:3, :3].T @ T_ee_b[:3, :3]) @ R_ee_cam


def choose_pairs(T_base_ee: Sequence[np.ndarray], R_ee_cam: np.ndarray, max_pairs: int) -> list[tuple[int, int]]:
    """Pairs (i, j) whose relative rotation is MIN..MAX_PAIR_ANGLE_DEG and where the hand-eye and its inverse
    predict rotations >= MIN_DISCRIMINATION_DEG apart; the most discriminating first, each image in at most
    two pairs (evidence spread over the capture)."""
    R_inv = R_ee_cam.T
    cand = []
    # at most MAX_CANDIDATE_VIEWS views, evenly over the capture: the pair search stays O(1) in its size
    views = np.unique(np.linspace(0, len(T_base_ee) - 1, min(len(T_base_ee), MAX_CANDIDATE_VIEWS)).round().astype(int))
    for a, i in enumerate(views):
        for j in views[a + 1:]:
            Pg = predicted_relative(T_base_ee[i], T_base_ee[j], R_ee_cam)
            ang = rotation_angle_deg(Pg)
            if not (MIN_PAIR_ANGLE_DEG <= ang <= MAX_PAIR_ANGLE_DEG):
                continue
            Pi = predicted_relative(T_base_ee[i], T_base_ee[j], R_inv)
            d = rotation_angle_deg(Pg.T @ Pi)
            if d >= MIN_DISCRIMINATION_DEG:
                cand.append((d, i, j))
    cand.sort(key=lambda c: -c[0])
    used: dict[int, int] = {}
    out = []
    for _, i, j in cand:
        i, j = int(i), int(j)
        if used.get(i, 0) >= 2 or used.get(j, 0) >= 2:
            continue
        out.append((i, j))
        used[i] = used.get(i, 0) + 1
        used[j] = used.get(j, 0) + 1
        if len(out) >= max_pairs:
            break
    return out


def neighbour_pairs(T_base_cam: Sequence[np.ndarray], max_pairs: int = MAX_CONSISTENCY_PAIRS) -> list[tuple[int, int]]:
    """Each view with the view nearest to it in viewing direction (>= MIN_NEIGHBOUR_ANGLE_DEG, <=
    MAX_PAIR_ANGLE_DEG apart: overlapping views, as the splats see them), deduplicated, up to `max_pairs` spread
    evenly over the capture. The pose consistency is measured on these: a per-view pose error shows in every
    pair, a hand-eye error in proportion to the pair's rotation, so near pairs keep a good calibration quiet."""
    n = len(T_base_cam)
    views = np.unique(np.linspace(0, n - 1, min(n, MAX_CANDIDATE_VIEWS)).round().astype(int))
    out: list[tuple[int, int]] = []
    for i in views:
        best = None
        for j in views:
            if j == i:
                continue
            ang = rotation_angle_deg(T_base_cam[i][:3, :3].T @ T_base_cam[j][:3, :3])
            if MIN_NEIGHBOUR_ANGLE_DEG <= ang <= MAX_PAIR_ANGLE_DEG and (best is None or ang < best[0]):
                best = (ang, int(j))
        if best is not None:
            p = (min(int(i), best[1]), max(int(i), best[1]))
            if p not in out:
                out.append(p)
    if len(out) > max_pairs:
        out = [out[k] for k in np.unique(np.linspace(0, len(out) - 1, max_pairs).round().astype(int))]
    return out


def consistency(rows: list[dict], size: tuple[int, int] | None) -> dict | None:
    """The pose-consistency score of pairs with sampson_px / sampson_floor_px / focal_px: median over the pairs
    (px at the matching resolution `size`, and mrad = px / focal) and its verdict: "bad" above BAD_MRAD, "warn"
    above WARN_MRAD (both only when >= FLOOR_FACTOR x the matches' own noise floor), else "ok"; None without
    MIN_PAIRS pairs."""
    if len(rows) < MIN_PAIRS:
        return None
    px = float(np.median([r["sampson_px"] for r in rows]))
    floor = float(np.median([r["sampson_floor_px"] for r in rows]))
    f = float(np.median([r["focal_px"] for r in rows]))
    mrad = 1000.0 * px / f
    above_floor = px >= FLOOR_FACTOR * floor
    verdict = "bad" if mrad > BAD_MRAD and above_floor else "warn" if mrad > WARN_MRAD and above_floor else "ok"
    return {"verdict": verdict, "sampson_median_px": round(px, 3), "sampson_floor_px": round(floor, 3),
            "sampson_median_mrad": round(mrad, 3), "focal_px": round(f, 2),
            "matching_size": list(size) if size else None, "warn_mrad": WARN_MRAD, "bad_mrad": BAD_MRAD,
            "warn_px": round(WARN_MRAD * f / 1000.0, 3), "bad_px": round(BAD_MRAD * f / 1000.0, 3),
            "pairs": len(rows), "per_pair": rows}


def _gray_small(path: Path, max_side: int) -> tuple[np.ndarray, float]:
    import cv2

    from splattwin.capture.dataset import load_image

    img = load_image(path)
    g = (np.clip(img.mean(axis=2), 0.0, 1.0) * 255).astype(np.uint8)
    s = min(1.0, max_side / max(g.shape[:2]))
    if s < 1.0:
        g = cv2.resize(g, (max(1, round(g.shape[1] * s)), max(1, round(g.shape[0] * s))), interpolation=cv2.INTER_AREA)
    return g, s


def _sift_points(sift, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints of `gray` as (positions [N,2] in OpenCV's pixel convention, centres at integers: SIFT's
    own +SIFT_BIAS_PX removed; descriptors [N,128] or None)."""
    kp, des = sift.detectAndCompute(gray, None)
    return np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2) - SIFT_BIAS_PX, des


def _normalised_points(uv: np.ndarray, cam, sx: float, sy: float) -> np.ndarray:
    """Points in OpenCV's pixel convention (pixel centres at integers; `_sift_points`) of the image resized
    by (sx, sy) -> normalised, undistorted camera coordinates [N,2] (`capture.undistort.rays_through` on the
    full-size camera). The camera's K puts pixel centres at +0.5 (`capture.camera`), so the points move by
    half a pixel first (else the principal point is half a pixel off: ~0.26 px of Sampson error on an exact
    pose at f 307 px); then the corner-origin coordinates scale exactly with the image."""
    return _rays(_full_size_pixels(uv, sx, sy), cam)


def _full_size_pixels(uv: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Points in OpenCV's pixel convention of the image resized by (sx, sy) -> pixels [N,2] of the full-size
    camera in the cameras' convention (pixel centres at +0.5: corner-origin coordinates scale exactly)."""
    return (uv + 0.5) / [sx, sy]


def _rays(uv: np.ndarray, cam) -> np.ndarray:
    """Pixels [N,2] of the full-size camera `cam`, in its convention (centres at +0.5) -> normalised,
    undistorted camera coordinates [N,2] (`capture.undistort.rays_through`)."""
    from splattwin.capture.undistort import rays_through

    x, y = rays_through(cam, uv[:, 0], uv[:, 1])
    return np.stack([x, y], axis=-1)


@dataclass
class PairMeasure:
    """One matched image pair: R = R_cam_a^T R_cam_b from the photos, the essential-matrix inliers in
    normalised camera coordinates (xa, xb [N,2]), the focal length f (px) and size (w, h) of the images at the
    matching resolution, and the inliers' median Sampson error (px there) under the photos' own essential
    matrix: the noise floor of the matching. ua, ub [N,2]: the same inliers in pixels of the full-size
    cameras cam_a, cam_b, in their convention (centres at +0.5; for re-normalising them under other
    intrinsics, `intrinsics_check`)."""

    R: np.ndarray
    inliers: int
    xa: np.ndarray
    xb: np.ndarray
    f: float
    size: tuple[int, int]
    floor_px: float
    ua: np.ndarray | None = None
    ub: np.ndarray | None = None
    cam_a: object = None
    cam_b: object = None


def sampson_px(xa: np.ndarray, xb: np.ndarray, R_ba: np.ndarray, t_ba: np.ndarray, f: float) -> np.ndarray:
    """Sampson (first-order geometric) epipolar error, in px of focal length `f`, of normalised matches
    xa <-> xb [N,2] under the relative pose x_b = R_ba x_a + t_ba (E = [t]x R; the scale of t does not matter)."""
    return np.abs(_signed_sampson_px(xa, xb, R_ba, t_ba, f))


def _signed_sampson_px(xa: np.ndarray, xb: np.ndarray, R_ba: np.ndarray, t_ba: np.ndarray, f: float) -> np.ndarray:
    """`sampson_px` with the sign of x_b^T E x_a: a residual smooth through 0, for least squares. xa, xb
    [..., N, 2] (leading axes: several hypotheses at once) -> [..., N]."""
    t = np.asarray(t_ba, dtype=np.float64)
    E = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]]) @ np.asarray(R_ba, dtype=np.float64)
    a = np.concatenate([xa, np.ones(xa.shape[:-1] + (1,))], axis=-1)
    b = np.concatenate([xb, np.ones(xb.shape[:-1] + (1,))], axis=-1)
    Ea, Eb = a @ E.T, b @ E
    den = Ea[..., 0] ** 2 + Ea[..., 1] ** 2 + Eb[..., 0] ** 2 + Eb[..., 1] ** 2
    return np.sum(b * Ea, axis=-1) / np.sqrt(np.maximum(den, 1e-300)) * f


def measure_pair(path_a: Path, path_b: Path, cam_a, cam_b, max_side: int = MAX_SIDE,
                 cache: dict | None = None) -> PairMeasure | None:
    """The relative rotation and the essential-matrix inliers of two photos (SIFT, ratio test, essential matrix
    with RANSAC and the cameras' intrinsics, cheirality), or None when they do not match well enough."""
    import cv2

    cache = {} if cache is None else cache
    sift = cv2.SIFT_create(nfeatures=2000)
    feats = []
    for p, cam in ((path_a, cam_a), (path_b, cam_b)):
        if p not in cache:
            g, s = _gray_small(p, max_side)
            pts, des = _sift_points(sift, g)
            sx, sy = g.shape[1] / cam.width, g.shape[0] / cam.height
            cache[p] = (pts, des, sx, sy, (int(g.shape[1]), int(g.shape[0])))
        feats.append(cache[p])
    (ua, da, sxa, sya, size), (ub, db, sxb, syb, _) = feats
    if da is None or db is None or len(ua) < MIN_INLIERS or len(ub) < MIN_INLIERS:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    pa = _full_size_pixels(ua[[m.queryIdx for m in good]], sxa, sya)  # the full-size cameras' pixels
    pb = _full_size_pixels(ub[[m.trainIdx for m in good]], sxb, syb)
    xa, xb = _rays(pa, cam_a), _rays(pb, cam_b)
    f = 0.5 * (cam_a.fx * sxa + cam_b.fx * sxb)
    E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.0 / f)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, mask2 = cv2.recoverPose(E, xa, xb, np.eye(3), mask=mask)
    if n < MIN_INLIERS:
        return None
    keep = mask2.ravel() > 0
    xa, xb = xa[keep], xb[keep]
    floor = float(np.median(sampson_px(xa, xb, R, t.ravel(), f)))
    # OpenCV: x_b = R x_a + t, i.e. R = R_cam_b^T R_cam_a
    return PairMeasure(R.T, int(n), xa, xb, float(f), size, floor, pa[keep], pb[keep], cam_a, cam_b)


# -- intrinsics and latency: the parameter that best explains the matches, the poses held fixed -------------
TRUNC_PX = 2.0               # a match's Sampson error counts at most this much (px at the matching resolution):
#                              outliers cannot pull the scans, and the truncated mean is smooth where a median jumps
BOOTSTRAP = 200              # resamples (pairs, then matches within each) for the estimates' 1-sigma
FOCAL_SCALES = (0.8, 1.25)   # focal-length scales scanned
FOCAL_WARN_REL = 0.015       # warn above 1.5 % with a clear minimum (see intrinsics_check)
LATENCY_RANGE_S = 0.1        # time offsets scanned: +-100 ms
LATENCY_WARN_S = 0.015       # warn above 15 ms with a clear minimum (see latency_check)
CLEAR_SIGMAS = 2.5           # "clear minimum": the estimate this many of its sigmas away from the given value
CLEAR_GAIN = 0.02            # and its truncated-mean Sampson error >= 2 % below the given value's
PP_RANGE_REL = 0.05          # principal-point offsets scanned: +- this x the image's longer side (+-16 px at 320)
PP_COARSE_STEPS = 8          # grid steps each way (2 px at 320x240) for the start of the joint fit
GN_ITERS = 10                # Gauss-Newton steps of the joint fit (focal scale, principal point) at most
PP_WARN_REL = 0.01           # warn above this x the focal length (px), with a clear minimum (see intrinsics_check)
FIT_FLOOR_FACTOR = 1.0       # the focal explains the misfit only if, scaled, the poses fit: Sampson median <=
#                              the matches' own noise floor (or half the warning level); else the poses are off
#                              and the focal scale absorbs their errors (measured: s = 0.80-1.08 with 3 mm /
#                              0.3 deg pose noise or a 1 cm / 2 deg hand-eye, 0.96 with 20 ms of latency; their
#                              medians at s 0.35-1.6 px, exact poses 0.14 px, the floor 0.25 px)


def _truncated(errors: list[np.ndarray]) -> list[np.ndarray]:
    return [np.minimum(e, TRUNC_PX) for e in errors]


def _tmean(errors: list[np.ndarray]) -> float:
    """The statistic the scans minimise: the mean over the pairs of each pair's truncated-mean error (px)."""
    return float(np.mean([e.mean() for e in _truncated(errors)]))


def _score(errors_at: Callable, values: list) -> tuple[list[np.ndarray], np.ndarray]:
    """Each pair's truncated Sampson errors at every value ([K, N_p] per pair) and the score per value [K]:
    the mean over the pairs of each pair's truncated mean."""
    E = [np.stack(z) for z in zip(*[_truncated(errors_at(v)) for v in values])]
    return E, np.mean([e.mean(axis=1) for e in E], axis=0)


def _bootstrap_argmin(E: list[np.ndarray], seed: int) -> np.ndarray:
    """The index of the best of K values [BOOTSTRAP] in each bootstrap resample of the per-pair errors E
    ([K, N_p] per pair; `_score`): pairs resampled first (a pose error of one view moves a whole pair),
    then the matches within each."""
    boot = np.zeros((E[0].shape[0], BOOTSTRAP))
    for e, w in zip(E, _bootstrap_weights([e.shape[1] for e in E], seed)):
        boot += e @ w
    return np.argmin(boot, axis=0)


def _bootstrap_weights(sizes: list[int], seed: int) -> list[np.ndarray]:
    """Per pair of `sizes[p]` matches, each match's weight [N_p, BOOTSTRAP] in each resample of a mean over
    the pairs of per-pair means: pairs resampled first, then the matches within each (weights sum to 1)."""
    rng = np.random.default_rng(seed)
    P = len(sizes)
    pair_w = rng.multinomial(P, np.full(P, 1.0 / P), size=BOOTSTRAP).T / P          # [P, B]
    return [rng.multinomial(n, np.full(n, 1.0 / n), size=BOOTSTRAP).T / n * pair_w[p]   # [N_p, B]
            for p, n in enumerate(sizes)]


def _scan(errors_at: Callable[[float], list[np.ndarray]], coarse: np.ndarray, fine_step: float,
          given: float, seed: int = 0) -> dict:
    """Minimise the mean over the pairs of each pair's truncated-mean Sampson error (px) over a parameter:
    a coarse scan, then a fine one (step `fine_step`) about its best value with a parabola through the best
    three; 1 sigma of the estimate from a bootstrap over pairs and matches (the fine grid's argmin per
    resample; pairs first, since a pose error of one view moves a whole pair). `given`: the value in use
    (its error is reported, and the gain). Returns value, sigma, error_px_given, error_px_best, curve
    (coarse values and errors), the fine grid's edges."""
    def score(vals):
        return _score(errors_at, [float(v) for v in vals])

    _, sc = score(coarse)
    k = int(np.argmin(sc))
    lo = coarse[max(k - 1, 0)]
    hi = coarse[min(k + 1, len(coarse) - 1)]
    fine = np.arange(lo, hi + 0.5 * fine_step, fine_step)
    E, sf = score(fine)
    kf = int(np.argmin(sf))
    best = float(fine[kf])
    if 0 < kf < len(fine) - 1:  # vertex of the parabola through the best three
        y0, y1, y2 = sf[kf - 1:kf + 2]
        den = y0 - 2 * y1 + y2
        if den > 0:
            best += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) * fine_step
    picks = fine[_bootstrap_argmin(E, seed)]
    eg, eb = errors_at(float(given)), errors_at(best)
    err_given = float(np.mean([e.mean() for e in _truncated(eg)]))
    err_best = float(np.mean([e.mean() for e in _truncated(eb)]))
    return {"value": best, "sigma": float(np.std(picks)), "error_px_given": err_given, "error_px_best": err_best,
            # the pose-consistency statistic (median over the pairs of their median Sampson error, px)
            "median_px_given": float(np.median([np.median(e) for e in eg])),
            "median_px_best": float(np.median([np.median(e) for e in eb])),
            "curve": [[round(float(v), 6), round(float(x), 4)] for v, x in zip(coarse, sc)],
            "fine_range": [float(fine[0]), float(fine[-1])]}


def _scaled_camera(cam, s: float):
    """`cam` with its focal lengths times s (principal point and distortion kept)."""
    from dataclasses import replace

    K = np.array(cam.K, dtype=np.float64)
    K[0, 0] *= s
    K[1, 1] *= s
    return replace(cam, K=K)


def _principal_point_start(measures: list[tuple[int, int, PairMeasure]], rel: list[np.ndarray], s: float) -> np.ndarray:
    """The principal-point offset (dcx, dcy) (px of the full-size cameras, added to every camera's cx, cy;
    focal lengths times `s`) of least truncated-mean Sampson error (`_score`) on a grid of +-PP_RANGE_REL x
    the longer image side (PP_COARSE_STEPS steps each way), the relative poses `rel` (camera a -> b) held
    fixed: where `_intrinsics_fit` starts. Moving the principal point by dc reads every pixel at uv - dc,
    so the rays are taken to first order in dc here (their derivative in the pixel, central differences):
    exact without lens distortion, and the grid only has to land in the right basin."""
    base = []
    for (_, _, m), T_ba in zip(measures, rel):
        per_cam = []
        for uv, cam in ((m.ua, m.cam_a), (m.ub, m.cam_b)):
            c = _scaled_camera(cam, s)
            dx = (_rays(uv + [1.0, 0.0], c) - _rays(uv - [1.0, 0.0], c)) / 2.0   # d ray / d u, per point
            dy = (_rays(uv + [0.0, 1.0], c) - _rays(uv - [0.0, 1.0], c)) / 2.0
            per_cam.append((_rays(uv, c), dx, dy))
        base.append((per_cam, T_ba, m.f * s))

    step = _pp_range_px(measures) / PP_COARSE_STEPS
    ax = np.arange(-PP_COARSE_STEPS, PP_COARSE_STEPS + 1) * step
    grid = np.array([(x, y) for y in ax for x in ax])            # [K, 2]
    gx, gy = grid[:, 0, None, None], grid[:, 1, None, None]     # the whole grid at once: [K, N, 2] rays per pair
    score = np.zeros(len(grid))
    for ((xa, ax_, ay_), (xb, bx, by)), T_ba, f in base:
        e = np.abs(_signed_sampson_px(xa - ax_ * gx - ay_ * gy, xb - bx * gx - by * gy, T_ba[:3, :3], T_ba[:3, 3], f))
        score += np.minimum(e, TRUNC_PX).mean(axis=1) / len(base)   # `_score`'s statistic
    return grid[int(np.argmin(score))].astype(np.float64)


def _pp_range_px(measures: list[tuple[int, int, PairMeasure]]) -> float:
    """The principal-point offsets searched: +- this many px of the full-size cameras (PP_RANGE_REL)."""
    return PP_RANGE_REL * float(np.median([max(m.cam_a.width, m.cam_a.height) for _, _, m in measures]))


def _gauss_newton(residuals: Callable[[np.ndarray], list[np.ndarray]], start, h, lo, hi, seed: int = 0) -> dict:
    """Parameters p (within lo..hi) minimising the matches' squared signed Sampson errors `residuals(p)` (per
    pair, px at the matching resolution; those over TRUNC_PX left out at each step; every pair weighted
    equally, as in `_score`): Gauss-Newton from `start` (central differences, steps h). 1 sigma of each from
    the bootstrap of `_scan` (`_bootstrap_weights`), one Gauss-Newton step per resample from the solution.
    Returns value, sigma and error(p) (per-pair absolute Sampson errors at p)."""
    h, lo, hi = (np.asarray(v, dtype=np.float64) for v in (h, lo, hi))
    k_n = len(h)

    def linearise(p: np.ndarray):
        r = residuals(p)
        cols = []
        for k in range(k_n):
            e = np.zeros(k_n)
            e[k] = h[k]
            plus, minus = residuals(p + e), residuals(p - e)
            cols.append([(a - b) / (2 * h[k]) for a, b in zip(plus, minus)])
        J = [np.stack([cols[k][q] for k in range(k_n)], axis=1) for q in range(len(r))]   # per pair [N_p, K]
        return r, J

    def normal(J, r, w):
        A = sum((Jq * wq[:, None]).T @ Jq for Jq, wq in zip(J, w))
        return A, sum((Jq * wq[:, None]).T @ rq for Jq, wq, rq in zip(J, w, r))

    p = np.array(start, dtype=np.float64)
    for _ in range(GN_ITERS):
        r, J = linearise(p)
        A, g = normal(J, r, [(np.abs(rq) < TRUNC_PX) / (len(rq) * len(r)) for rq in r])
        step = -np.linalg.solve(A + 1e-9 * np.diag(np.diag(A)) + 1e-12 * np.eye(k_n), g)
        p = np.clip(p + step, lo, hi)
        if np.all(np.abs(step) < 0.01 * h):
            break
    r, J = linearise(p)
    inl = [np.abs(rq) < TRUNC_PX for rq in r]
    W = _bootstrap_weights([len(rq) for rq in r], seed)
    picks = []
    for b in range(BOOTSTRAP):
        A, g = normal(J, r, [Wq[:, b] * iq for Wq, iq in zip(W, inl)])
        try:
            picks.append(p - np.linalg.solve(A, g))
        except np.linalg.LinAlgError:   # a resample of too few matches: no estimate from it
            continue

    def error(q) -> list[np.ndarray]:
        return [np.abs(e) for e in residuals(np.asarray(q, dtype=np.float64))]

    return {"value": p, "sigma": np.std(picks, axis=0) if picks else np.full(k_n, np.inf), "error": error}


def _intrinsics_fit(measures: list[tuple[int, int, PairMeasure]], rel: list[np.ndarray], start: np.ndarray,
                    seed: int = 0) -> dict:
    """Focal scale s and principal-point offset (dcx, dcy) (px, full size) together, from `start`, the poses
    `rel` (camera a -> b) held fixed (`_gauss_newton`). The two are estimated together because they trade
    off: with mostly sideways baselines a cx offset of 5 px moved the focal scan's minimum by 6 %
    (`bench/pose_checks.py`). Returns `_gauss_newton`'s dict (value [s, dcx, dcy]) and range_px."""
    rng_px = _pp_range_px(measures)

    def residuals(p: np.ndarray) -> list[np.ndarray]:
        # the camera with fx, fy times s and cx, cy + dc reads pixel uv as the given camera reads
        # c + (uv - dc - c) / s (c = cx, cy): no camera to build per evaluation
        out = []
        for (_, _, m), T_ba in zip(measures, rel):
            ca, cb = np.array([m.cam_a.cx, m.cam_a.cy]), np.array([m.cam_b.cx, m.cam_b.cy])
            xa = _rays(ca + (m.ua - p[1:] - ca) / p[0], m.cam_a)
            xb = _rays(cb + (m.ub - p[1:] - cb) / p[0], m.cam_b)
            out.append(_signed_sampson_px(xa, xb, T_ba[:3, :3], T_ba[:3, 3], m.f * p[0]))   # px as in `_scan`
        return out

    return {**_gauss_newton(residuals, start, [1e-3, 0.1, 0.1], [FOCAL_SCALES[0], -rng_px, -rng_px],
                            [FOCAL_SCALES[1], rng_px, rng_px], seed), "range_px": rng_px}


def _rotation_fit(measures: list[tuple[int, int, PairMeasure]], rel: list[np.ndarray], s: float,
                  dc: np.ndarray, seed: int = 0) -> dict:
    """The other explanation of a principal-point offset: every camera turned by one small rotation in its
    own frame (about x, y; rad) from the poses, as a hand-eye rotation error does. To first order the two
    are the same (a turn by a moves the image by f a); they differ by ~a u^2 / f towards the image's edges.
    Fitted (`_gauss_newton`, focal scale s kept) from the turn matching `dc`, either sign. Returns
    `_gauss_newton`'s dict (value [wx, wy])."""
    from scipy.spatial.transform import Rotation

    cams = [(_scaled_camera(m.cam_a, s), _scaled_camera(m.cam_b, s)) for _, _, m in measures]
    rays = [(_rays(m.ua, ca), _rays(m.ub, cb)) for (_, _, m), (ca, cb) in zip(measures, cams)]

    def residuals(p: np.ndarray) -> list[np.ndarray]:
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec([p[0], p[1], 0.0]).as_matrix()   # camera' = camera @ E
        out = []
        for (_, _, m), T_ba, (xa, xb) in zip(measures, rel, rays):
            T = E.T @ T_ba @ E
            out.append(_signed_sampson_px(xa, xb, T[:3, :3], T[:3, 3], m.f * s))
        return out

    f = float(np.median([c.fx for c, _ in cams]))
    lim = np.radians(10.0)
    starts = [np.zeros(2), np.array([dc[1], -dc[0]]) / f, np.array([-dc[1], dc[0]]) / f]
    start = min(starts, key=lambda q: _tmean([np.abs(e) for e in residuals(q)]))
    return _gauss_newton(residuals, start, [1e-4, 1e-4], [-lim, -lim], [lim, lim], seed)


def intrinsics_check(measures: list[tuple[int, int, PairMeasure]], T_world_cam: Sequence[np.ndarray],
                     where: Path | str | None = None, seed: int = 0) -> dict | None:
    """The focal-length scale s (fx and fy times s) and the principal-point offset under which the matched
    near pairs best fit the epipolar geometry of the poses T_world_cam, held fixed: a scan of s over
    FOCAL_SCALES (`_scan`: truncated-mean Sampson error, px at the matching resolution), the matches
    re-normalised through the scaled cameras (`capture.undistort.rays_through`, the distortion kept).
    Verdict "warn" when |s - 1| > FOCAL_WARN_REL with a clear minimum (s at least CLEAR_SIGMAS of its
    bootstrap sigma from 1 and the error CLEAR_GAIN below that of the given focal), "undetermined" when the
    poses do not fit the photos even at s (FIT_FLOOR_FACTOR: pose errors, not the focal; the pose
    consistency warns), else "ok"; None without MIN_PAIRS pairs. `where`: the intrinsics' source, for the
    record and the warning.

    Then the principal point (`_principal_point_start`, `_intrinsics_fit`): the offset (dcx, dcy) (px of the
    full-size cameras, added to cx, cy) fitted together with the focal scale, since the two trade off. Its
    verdict: "warn" when |dc| > PP_WARN_REL x fx with a clear minimum (CLEAR_SIGMAS of its bootstrap
    sigma, CLEAR_GAIN), "undetermined" when the poses do not fit even at it, or when every camera turned by
    one small rotation in its own frame (`_rotation_fit`: a hand-eye rotation error, the same to first
    order) fits as well, else "ok". Where the offset fits better than the turn, the focal scale reported is
    the joint fit's (the scan's, at the principal point as given, absorbs the offset: a cx 5 px off read
    s = 1.063), and the poses fit at it.

    Measured on the embedded scene as a TUM capture (320x240, f = 307.5 px, 8 near pairs, exact poses):
    focal given x1.00 / 1.01 / 1.02 / 1.05 / 0.98 -> s = 1.001 / 0.992 / 0.982 / 0.954 / 1.022 (true 1 /
    0.990 / 0.980 / 0.952 / 1.020), bootstrap sigma ~0.004 (`bench/pose_checks.py`); the 1.5 % threshold is
    above 2.5 sigma there, so 2 % errors warn and 1 % ones do not (their depth error, 1 %, is below the depth
    check's 5 % band too).
    Principal point moved by 5 / 10 px in x: found -4.9 / -9.9 px (sigma 0.2), in y: -4.5 / -9.5 (sigma 0.8;
    +0.4 px with the true one), by (-7, +6): (+7.2, -5.5), all warned (3.1 px threshold); 2 px: not warned
    (x: undetermined, a turn fits as well; y: ok); a 1 cm / 2 deg hand-eye error, whose turn a principal
    point offset of 10-14 px imitates: undetermined in 3 of 3 seeds (the turn fits better), no warning."""
    measures = [(i, j, m) for i, j, m in measures if m.ua is not None and m.cam_a is not None]
    if len(measures) < MIN_PAIRS:
        return None
    rel = [np.linalg.inv(T_world_cam[j]) @ T_world_cam[i] for i, j, _ in measures]  # camera a -> camera b

    def errors_at(s: float) -> list[np.ndarray]:
        out = []
        for (_, _, m), T_ba in zip(measures, rel):
            xa = _rays(m.ua, _scaled_camera(m.cam_a, s))
            xb = _rays(m.ub, _scaled_camera(m.cam_b, s))
            out.append(sampson_px(xa, xb, T_ba[:3, :3], T_ba[:3, 3], m.f * s))
        return out

    lo, hi = np.log(FOCAL_SCALES[0]), np.log(FOCAL_SCALES[1])
    r = _scan(errors_at, np.exp(np.arange(lo, hi + 1e-9, 0.01)), 0.001, 1.0, seed)  # 1 % then 0.1 % steps
    s, sig = r["value"], r["sigma"]
    gain = 1.0 - r["error_px_best"] / max(r["error_px_given"], 1e-12)
    clear = abs(s - 1.0) >= CLEAR_SIGMAS * max(sig, 1e-4) and gain >= CLEAR_GAIN
    fx = float(np.median([m.cam_a.fx for _, _, m in measures]))
    f = float(np.median([m.f for _, _, m in measures]))
    floor = float(np.median([m.floor_px for _, _, m in measures]))
    # the principal point, with the focal scale again: the two trade off (`_intrinsics_fit`)
    scan_s = s
    j = _intrinsics_fit(measures, rel, np.r_[s, _principal_point_start(measures, rel, s)], seed)
    sj, dc, sj_sig, dsig = float(j["value"][0]), j["value"][1:], float(j["sigma"][0]), j["sigma"][1:]
    e_best, e_pp_given = j["error"](j["value"]), j["error"]([sj, 0.0, 0.0])
    pp_gain = 1.0 - _tmean(e_best) / max(_tmean(e_pp_given), 1e-12)
    pp_clear = float(np.hypot(*(dc / np.maximum(dsig, 0.05)))) >= CLEAR_SIGMAS and pp_gain >= CLEAR_GAIN
    pp_warn_px = PP_WARN_REL * fx
    med_best = float(np.median([np.median(e) for e in e_best]))
    fit_px = max(FIT_FLOOR_FACTOR * floor, 0.5 * WARN_MRAD * f / 1000.0)
    fits = r["median_px_best"] <= fit_px   # at the focal scan's best, the principal point as given
    rot, turn_as_good = None, False
    if pp_clear and med_best <= fit_px:
        # the poses fit once the principal point moves; a turn of every camera in its own frame (a hand-eye
        # rotation error) would do the same to first order: the offset counts only where it fits better
        rot = _rotation_fit(measures, rel, sj, dc, seed)
        turn_as_good = _tmean(rot["error"](rot["value"])) <= _tmean(e_best)
    pp_explains = pp_clear and med_best <= fit_px and not turn_as_good
    if pp_explains:   # the focal at the principal point found: the scan's, at the one given, absorbed the
        #               offset (a cx 2-5 px off moved it by 0.5-6 %); else the scan's (its sigma about half)
        fits = True
        e_f_given = j["error"]([1.0, *dc])
        s, sig = sj, sj_sig
        clear = abs(s - 1.0) >= CLEAR_SIGMAS * max(sig, 1e-4) and \
            1.0 - _tmean(e_best) / max(_tmean(e_f_given), 1e-12) >= CLEAR_GAIN
        r = {**r, "error_px_best": _tmean(e_best), "median_px_best": med_best}
    verdict = "undetermined" if not fits else "warn" if abs(s - 1.0) > FOCAL_WARN_REL and clear else "ok"
    pp_verdict = ("warn" if pp_explains and float(np.hypot(*dc)) > pp_warn_px else
                  "ok" if pp_explains or (fits and not pp_clear) else "undetermined")
    cx = float(np.median([m.cam_a.cx for _, _, m in measures]))
    cy = float(np.median([m.cam_a.cy for _, _, m in measures]))
    return {"verdict": verdict, "poses_fit": bool(fits),
            "focal_scale": round(s, 4), "focal_scale_sigma": round(sig, 4), "clear_minimum": bool(clear),
            "focal_px_given": round(fx, 2), "focal_px_best": round(fx * s, 2),
            "error_px_given": round(r["error_px_given"], 4), "error_px_best": round(r["error_px_best"], 4),
            "error": f"mean over the pairs of the truncated (<= {TRUNC_PX:g} px) mean Sampson error",
            "sampson_median_px_given": round(r["median_px_given"], 3),
            "sampson_median_px_best": round(r["median_px_best"], 3),
            "warn_rel": FOCAL_WARN_REL, "pairs": len(measures),
            "intrinsics_file": None if where is None else str(where),
            "curve_scale_error_px": r["curve"],
            "principal_point_verdict": pp_verdict,
            "principal_point_offset_px": [round(float(v), 2) for v in dc],
            "principal_point_sigma_px": [round(float(v), 2) for v in dsig],
            "principal_point_clear_minimum": bool(pp_clear),
            "principal_point_px_given": [round(cx, 2), round(cy, 2)],
            "principal_point_px_best": [round(cx + float(dc[0]), 2), round(cy + float(dc[1]), 2)],
            "principal_point_error_px_given": round(_tmean(e_pp_given), 4),
            "principal_point_error_px_best": round(_tmean(e_best), 4),
            "principal_point_sampson_median_px_best": round(med_best, 3),
            "principal_point_warn_px": round(pp_warn_px, 2),
            "principal_point_range_px": round(j["range_px"], 2),
            "principal_point_turn_as_good": bool(turn_as_good),
            "principal_point_turn_deg": None if rot is None else [round(float(np.degrees(v)), 3) for v in rot["value"]],
            "principal_point_turn_error_px": None if rot is None else round(_tmean(rot["error"](rot["value"])), 4),
            "focal_scale_scan": round(scan_s, 4), "focal_scale_joint": round(sj, 4),
            "focal_scale_joint_sigma": round(sj_sig, 4)}


def intrinsics_message(c: dict) -> str:
    """The warning for an `intrinsics_check` verdict "warn"."""
    pct = 100.0 * (c["focal_scale"] - 1.0)
    where = c.get("intrinsics_file")
    return (f"the camera intrinsics{f' ({where})' if where else ''} look off: with the poses held fixed, the "
            f"matched features of {c['pairs']} image pairs fit the epipolar geometry best with the focal length "
            f"scaled by {c['focal_scale']:.3f} (+-{c['focal_scale_sigma']:.3f}, {pct:+.1f} %: fx "
            f"{c['focal_px_given']:.1f} -> {c['focal_px_best']:.1f} px at full size; error "
            f"{c['error_px_given']:.3f} -> {c['error_px_best']:.3f} px). A focal length off by {abs(pct):.1f} % "
            f"scales depth by as much and misplaces objects: re-calibrate "
            f"the camera (the intrinsics of the stream the images come from, at this resolution) or correct fx/fy "
            f"in the intrinsics file")


def principal_point_message(c: dict) -> str:
    """The warning for an `intrinsics_check` principal_point_verdict "warn"."""
    where = c.get("intrinsics_file")
    (dx, dy), (sx, sy) = c["principal_point_offset_px"], c["principal_point_sigma_px"]
    (gx, gy), (bx, by) = c["principal_point_px_given"], c["principal_point_px_best"]
    mrad = 1000.0 * float(np.hypot(dx, dy)) / c["focal_px_given"]
    turn = c.get("principal_point_turn_error_px")
    return (f"the camera's principal point{f' ({where})' if where else ''} looks off: with the poses held fixed, "
            f"the matched features of {c['pairs']} image pairs fit the epipolar geometry best with it moved by "
            f"({dx:+.1f}, {dy:+.1f}) px (+-{sx:.1f}, +-{sy:.1f}): cx, cy ({gx:.1f}, {gy:.1f}) -> ({bx:.1f}, "
            f"{by:.1f}) px at full size, pixel centres at +0.5 (error {c['principal_point_error_px_given']:.3f} -> "
            f"{c['principal_point_error_px_best']:.3f} px"
            + (f"; every camera turned instead, as by a hand-eye rotation error: {turn:.3f} px" if turn is not None
               else "")
            + f"). A principal point off by {np.hypot(dx, dy):.1f} px turns every camera ray by {mrad:.0f} mrad "
            f"(~{mrad:.0f} mm per metre of distance) and misplaces objects: re-calibrate the camera (the "
            f"intrinsics of the stream the images come from, at this resolution) or correct cx/cy in the intrinsics "
            f"file (the image centre given for the calibrated principal point is a common cause)")


def latency_check(measures: list[tuple[int, int, PairMeasure]],
                  poses_at: Callable[[float], tuple[np.ndarray, np.ndarray]], offset_s: float = 0.0,
                  seed: int = 0) -> dict | None:
    """The time offset dt (s) between image and pose timestamps that best explains the matched near pairs:
    `poses_at(offset)` gives (T_world_cam [V,4,4], ok [V]) of the views at their image time + offset (poses
    interpolated, SLERP + linear); dt is scanned over offset_s +- LATENCY_RANGE_S (`_scan`, 5 ms then 1 ms
    steps) on the pairs posed at every offset scanned. `offset_s`: the offset in use (--poses.time-offset-ms).
    Verdict "warn" when |dt - offset_s| > LATENCY_WARN_S with a clear minimum (CLEAR_SIGMAS, CLEAR_GAIN as in
    `intrinsics_check`), "undetermined" when the error hardly changes over the whole scan (by less than
    CLEAR_GAIN: the arm still or at constant velocity between the matched views, so no offset changes their
    relative poses), else "ok"; None without MIN_PAIRS pairs."""
    coarse = offset_s + np.arange(-LATENCY_RANGE_S, LATENCY_RANGE_S + 1e-9, 0.005)
    cache = {}

    def at(dt: float):
        key = round(dt, 6)
        if key not in cache:
            cache[key] = poses_at(dt)
        return cache[key]

    ok_all = np.logical_and.reduce([at(float(d))[1] for d in coarse])
    measures = [(i, j, m) for i, j, m in measures if ok_all[i] and ok_all[j]]
    if len(measures) < MIN_PAIRS:
        return None

    def errors_at(dt: float) -> list[np.ndarray]:
        T, ok = at(dt)
        out = []
        for i, j, m in measures:
            if not (ok[i] and ok[j]):  # between the coarse offsets where all were posed: cannot happen, but count
                out.append(np.full(len(m.xa), TRUNC_PX))
                continue
            T_ba = np.linalg.inv(T[j]) @ T[i]
            out.append(sampson_px(m.xa, m.xb, T_ba[:3, :3], T_ba[:3, 3], m.f))
        return out

    r = _scan(errors_at, coarse, 0.001, offset_s, seed)
    dt, sig = r["value"], r["sigma"]
    gain = 1.0 - r["error_px_best"] / max(r["error_px_given"], 1e-12)
    clear = abs(dt - offset_s) >= CLEAR_SIGMAS * max(sig, 1e-4) and gain >= CLEAR_GAIN
    # a path at constant velocity (or a still arm) keeps every relative pose whatever the offset: the curve is
    # flat, and its argmin says nothing
    errs = [e for _, e in r["curve"]]
    observable = (max(errs) - min(errs)) >= CLEAR_GAIN * max(min(errs), 1e-12)
    verdict = ("undetermined" if not observable else
               "warn" if abs(dt - offset_s) > LATENCY_WARN_S and clear else "ok")
    return {"verdict": verdict, "observable": bool(observable),
            "time_offset_ms": round(1000.0 * dt, 1), "time_offset_sigma_ms": round(1000.0 * sig, 1),
            "offset_in_use_ms": round(1000.0 * offset_s, 1), "clear_minimum": bool(clear),
            "error_px_given": round(r["error_px_given"], 4), "error_px_best": round(r["error_px_best"], 4),
            "error": f"mean over the pairs of the truncated (<= {TRUNC_PX:g} px) mean Sampson error",
            "warn_ms": 1000.0 * LATENCY_WARN_S, "pairs": len(measures),
            "convention": "pose of an image stamped t taken at t + time_offset (--poses.time-offset-ms)",
            "curve_ms_error_px": [[round(1000.0 * v, 1), e] for v, e in r["curve"]]}


def latency_message(c: dict, pose_file: Path | str | None = None) -> str:
    """The warning for a `latency_check` verdict "warn"."""
    return (f"the image and pose timestamps look offset: the matched features of {c['pairs']} image pairs fit the "
            f"poses best when each image takes the pose at its timestamp {c['time_offset_ms']:+.0f} ms "
            f"(+-{c['time_offset_sigma_ms']:.1f} ms; now {c['offset_in_use_ms']:+.0f} ms; error "
            f"{c['error_px_given']:.3f} -> {c['error_px_best']:.3f} px): camera latency or clocks out of sync"
            f"{f' ({pose_file})' if pose_file else ''}. Pass --poses.time-offset-ms={c['time_offset_ms']:.0f} "
            f"(build; splattwin poses: --time-offset-ms={c['time_offset_ms']:.0f}) to match the images to the "
            f"poses at that offset, or fix the "
            f"timestamps (hardware sync, or the camera driver's latency compensation)")


def measure_relative_rotation(path_a: Path, path_b: Path, cam_a, cam_b, max_side: int = MAX_SIDE,
                              cache: dict | None = None) -> tuple[np.ndarray, int] | None:
    """(R_cam_a^T R_cam_b, inliers) from the two photos (`measure_pair`), or None."""
    m = measure_pair(path_a, path_b, cam_a, cam_b, max_side, cache)
    return None if m is None else (m.R, m.inliers)


def evaluate(pairs: list[dict]) -> HandEyeCheck:
    """The verdict from pairs with residual_deg / inverse_residual_deg (see the module docstring)."""
    src = pairs[0]["source"] if pairs else "images"
    rows = [{k: v for k, v in p.items() if k != "source"} for p in pairs]
    if len(rows) < 2:
        return HandEyeCheck("undecided", src, rows)
    eg = np.array([p["residual_deg"] for p in rows])
    ei = np.array([p["inverse_residual_deg"] for p in rows])
    mg, mi = float(np.median(eg)), float(np.median(ei))
    wins = float(np.mean(ei < eg))
    if len(rows) >= MIN_PAIRS and mg >= STRONG_DEG and mi <= mg / 3.0 and wins >= 0.75:
        verdict = "inverted"
    elif mg >= 3.0 and mi < mg / 2.0 and wins > 0.5:
        verdict = "inverted?"
    elif mg > MISMATCH_DEG and len(rows) >= MIN_PAIRS:
        verdict = "mismatch"
    else:
        verdict = "consistent"
    return HandEyeCheck(verdict, src, rows, round(mg, 3), round(mi, 3))


def _pair_row(a: str, b: str, R_meas: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, R_ee_cam: np.ndarray,
              source: str, **extra) -> dict:
    eg = rotation_angle_deg(R_meas.T @ predicted_relative(T_a, T_b, R_ee_cam))
    ei = rotation_angle_deg(R_meas.T @ predicted_relative(T_a, T_b, R_ee_cam.T))
    return {"a": a, "b": b, "residual_deg": round(eg, 3), "inverse_residual_deg": round(ei, 3), "source": source,
            **extra}


def check_with_images(names: list[str], T_base_ee: list[np.ndarray], T_ee_cam: np.ndarray,
                      image_paths: list[Path], cameras: list, max_pairs: int = MAX_IMAGE_PAIRS) -> HandEyeCheck:
    """Relative rotations measured from up to `max_pairs` photo pairs against the robot's predictions, and
    the matches' Sampson error under the relative poses (rotation and translation) the robot predicts."""
    R = T_ee_cam[:3, :3]
    rows = []
    cache: dict = {}
    size = None
    # a few spare pairs in case some do not match
    for i, j in choose_pairs(T_base_ee, R, 3 * max_pairs):
        if len(rows) >= max_pairs:
            break
        try:
            m = measure_pair(Path(image_paths[i]), Path(image_paths[j]), cameras[i], cameras[j], cache=cache)
        except Exception as e:  # an unreadable image is someone else's error to report; no verdict from it
            log.debug("hand-eye check: pair %s, %s not measured: %s", names[i], names[j], e)
            m = None
        if m is None:
            continue
        T_ba = np.linalg.inv(T_base_ee[j] @ T_ee_cam) @ (T_base_ee[i] @ T_ee_cam)  # camera a -> camera b
        err = float(np.median(sampson_px(m.xa, m.xb, T_ba[:3, :3], T_ba[:3, 3], m.f)))
        size = size or m.size
        rows.append(_pair_row(names[i], names[j], m.R, T_base_ee[i], T_base_ee[j], R, "images", inliers=m.inliers,
                              sampson_px=round(err, 3), sampson_floor_px=round(m.floor_px, 3),
                              focal_px=round(m.f, 2)))
    res = evaluate(rows)
    res.source = "images"
    # pose consistency: near pairs (see neighbour_pairs), matched with the same feature cache
    res.consistency, res.measures = check_poses_with_images(names, [T @ T_ee_cam for T in T_base_ee], image_paths,
                                                            cameras, cache, size)
    return res


def check_poses_with_images(names: list[str], T_world_cam: list[np.ndarray], image_paths: list[Path], cameras: list,
                            cache: dict | None = None, size: tuple[int, int] | None = None
                            ) -> tuple[dict | None, list[tuple[int, int, PairMeasure]]]:
    """Pose consistency of camera poses T_world_cam (any metric world) with their photos: the `consistency`
    score of up to MAX_CONSISTENCY_PAIRS near pairs (`neighbour_pairs`), and the matched pairs themselves
    (i, j, PairMeasure) for `intrinsics_check` / `latency_check`."""
    cache = {} if cache is None else cache
    crow, measures = [], []
    for i, j in neighbour_pairs(T_world_cam):
        try:
            m = measure_pair(Path(image_paths[i]), Path(image_paths[j]), cameras[i], cameras[j], cache=cache)
        except Exception as e:  # an unreadable image is someone else's error to report
            log.debug("pose consistency: pair %s, %s not measured: %s", names[i], names[j], e)
            m = None
        if m is None:
            continue
        T_ba = np.linalg.inv(T_world_cam[j]) @ T_world_cam[i]  # camera a -> camera b: x_b = R x_a + t
        size = size or m.size
        measures.append((i, j, m))
        crow.append({"a": names[i], "b": names[j], "inliers": m.inliers,
                     "sampson_px": round(float(np.median(sampson_px(m.xa, m.xb, T_ba[:3, :3], T_ba[:3, 3], m.f))), 3),
                     "sampson_floor_px": round(m.floor_px, 3), "focal_px": round(m.f, 2)})
    return consistency(crow, size), measures


def check_with_rotations(names: list[str], T_base_ee: list[np.ndarray], T_ee_cam: np.ndarray,
                         R_world_cam: list[np.ndarray], max_pairs: int = MAX_SFM_PAIRS) -> HandEyeCheck:
    """Relative rotations of independently estimated cameras (an SfM model, any world frame)."""
    R = T_ee_cam[:3, :3]
    rows = [_pair_row(names[i], names[j], R_world_cam[i].T @ R_world_cam[j], T_base_ee[i], T_base_ee[j], R, "sfm")
            for i, j in choose_pairs(T_base_ee, R, max_pairs)]
    res = evaluate(rows)
    res.source = "sfm"
    return res


def report(chk: HandEyeCheck, where: Path | None, stop: bool = True,
           inverted_error: Callable[[str], Exception] | None = None) -> None:
    """Log the verdict; an "inverted" verdict raises (when `stop`) the error `inverted_error(message)`."""
    what = chk.describe()
    if chk.verdict == "inverted":
        msg = (f"the hand-eye looks inverted: {what}. The file holds T_cam_ee (the flange in the camera frame), "
               f"not T_ee_cam (the camera in the flange frame): invert it (OpenCV calibrateHandEye's "
               f"R/t_cam2gripper is T_ee_cam)")
        if stop and inverted_error is not None:
            raise inverted_error(msg + " (--no-check-hand-eye, in build --no-poses.check-hand-eye, skips this check)")
        log.warning("%s%s", msg, f" ({where})" if where else "")
    elif chk.verdict == "inverted?":
        log.warning("the hand-eye may be inverted (T_cam_ee given for T_ee_cam): %s; check %s", what,
                    where or "the hand-eye")
    elif chk.verdict == "mismatch":
        log.warning("the hand-eye does not match the photos: %s (a wrong hand-eye rotation, wrong intrinsics, "
                    "or poses that do not belong to these images?); check %s", what, where or "the hand-eye")
    elif chk.verdict == "consistent":
        log.info("hand-eye check: %s", what)
    else:
        log.info("hand-eye check undecided: %s (needs pairs whose relative rotation tells the hand-eye from its "
                 "inverse)", what)


def consistency_message(c: dict, where: Path | str | None = None, then: str | None = None,
                        robot: bool = True) -> str:
    """What the pose-consistency score says, for a warning (see `consistency`); `then`: what happens next
    (default: the remedy); `robot`: robot poses + hand-eye (`where`: the hand-eye's file), else known camera
    poses (`where`: their file)."""
    w, h = c.get("matching_size") or (None, None)
    at = f"{w}x{h} px matching resolution" if w else "the matching resolution"
    deg = c["sampson_median_mrad"] * 0.18 / np.pi
    then = then or ("remedy: --poses.method sfm with the same --robot-poses (SfM aligned to the robot poses: the "
                    "photos fix the relative poses, the robot the metric frame)")
    if not robot:
        return (f"the camera poses{f' ({where})' if where else ''} do not fit the photos: matched features of "
                f"{c['pairs']} neighbouring image pairs lie a median {c['sampson_median_px']:.2f} px ({at}; "
                f"{c['sampson_median_mrad']:.1f} mrad, ~{deg:.2f} deg) off the epipolar lines the poses predict (the "
                f"matches' own noise floor {c['sampson_floor_px']:.2f} px; warning above {c['warn_mrad']:g} mrad = "
                f"{c['warn_px']:.2f} px here). Likely causes: the hand-eye calibration the poses were computed with, "
                f"pose timestamps (see latency_check in poses_report.json), or the intrinsics (intrinsics_check). "
                f"{then[0].upper()}{then[1:]}")
    return (f"the robot poses do not fit the photos: matched features of {c['pairs']} neighbouring image pairs lie a "
            f"median {c['sampson_median_px']:.2f} px ({at}; {c['sampson_median_mrad']:.1f} mrad, ~{deg:.2f} deg) off "
            f"the epipolar lines the robot poses + hand-eye predict (the matches' own noise floor "
            f"{c['sampson_floor_px']:.2f} px; a good hand-eye calibration, ~3 mm / 0.5 deg, gives ~0.9 mrad; warning "
            f"above {c['warn_mrad']:g} mrad = {c['warn_px']:.2f} px here): the cameras are off by more than about "
            f"5 mm / 1 deg of hand-eye error or 1 mm / 0.1 deg per view, which blurs the splats and misplaces the "
            f"objects by centimetres. Likely causes: the hand-eye calibration{f' ({where})' if where else ''} "
            f"(re-calibrate, e.g. OpenCV calibrateHandEye with more, more varied poses), pose timestamps (joint "
            f"states read while the arm still moved: capture at standstill, or match the image times), or the "
            f"intrinsics (calibrate the camera). {then[0].upper()}{then[1:]}")
