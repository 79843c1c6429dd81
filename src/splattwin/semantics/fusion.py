"""Visibility-aware semantic fusion of 2D masks into per-Gaussian labels (paper section 3.2).

For every object label o and view j (all arrays numpy, N Gaussians, L object labels):
1. Visibility: Gaussian i is visible in view j when its centre projects inside the image and its camera
   z-depth agrees with the depth rendered from the splats at that pixel:
   |z_ij - D_j(u,v)| <= depth_tol + depth_tol_rel * D_j(u,v)   (metres).
2. Depth-guided isolation: the visible Gaussians whose projection falls inside mask M_jo are clustered
   on depth with DBSCAN (eps = 0.02 m, min_samples = 10). The largest cluster is the object; every
   Gaussian gets the soft gate w = exp(-(d / eps)^2), d = its depth distance to the largest cluster's
   depth interval (1 inside it, ~0.1 at 3 cm, ~0 for detached clusters > 5 cm away).
3. Weighted consensus: V_io = sum_j w_ij * [in mask]; label o when V_io >= tau = N_i / kappa with
   N_i = number of views where i is visible (kappa = 1.5).
4. Refinement (up to `iters` rounds): depth is re-rendered from the current labelled model without the
   floaters found so far (unlabelled Gaussians gated out *in front of* an object in most of their
   in-mask observations: ghosting artefacts that hide the surface behind them), visibility and votes
   are recomputed. Each round ends with iterative KNN boundary smoothing (up to `iters` passes, until
   < 0.1 % flip): low-confidence labels that disagree with a clear majority of their k nearest
   neighbours flip (this also labels never-visible interior/underside Gaussians). Rounds stop when no
   new floater is found (the next round would repeat the last one exactly).
5. Several objects: a Gaussian passing the consensus for several labels takes the one with the most
   weighted votes; everything else is background (0).
Each step is a function of its own, tested on hand-worked cases (tests/semantics/test_fusion_steps.py):
1 `project_to_pixels` + `visible_mask` (+ `grazing`), 2 `dbscan_1d` + `soft_gate`, per view
`view_observations`, 3 + 5 `consensus`, 4 `find_floaters` and the rounds of `fuse`, `smooth_labels`
(iterated `knn_smooth`).

DBSCAN on 1-D depth is done exactly by sorting (`dbscan_1d`) instead of scikit-learn: in 1-D the
eps-neighbourhood of a point is a contiguous range of the sorted depths (two binary searches), and core
points form one cluster exactly when consecutive core depths are <= eps apart, so the whole clustering
is O(n log n) numpy with the same core/noise labelling as scikit-learn (tested against it). The fusion
runs it views x objects x rounds times (~200 calls for the benchmark); scikit-learn's generic
neighbourhood queries would dominate the 10 s budget (7-10 s for one 200k-point DBSCAN here).

`naive_fusion` is the baseline of the published code: project centres into all views, count in-mask
votes, keep a fixed fraction of the views, no visibility and no isolation.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from splattwin import io
from splattwin.capture.camera import Camera
from splattwin.equality import dataclass_eq
from splattwin.errors import InputError, short_repr
from splattwin.semantics.masks import MaskSet, MaskWarning
from splattwin.semantics.label_render import DepthRenderer, PointDepth, project_to_pixels
from splattwin.semantics.options import FusionOptions
from splattwin.transforms import matrix_from_quat_wxyz

log = logging.getLogger(__name__)


@dataclass
class FusionResult:
    """Output of `fuse`: labels [N] int32 (0 background) and the evidence behind them.

    votes [N,L] weighted in-mask votes per object (columns follow `label_ids`), hits [N,L] unweighted
    in-mask visible counts, n_visible [N] number of views where visible, confidence [N] in [0,1],
    floaters [N] bool, names label -> object name, history per round.
    """

    labels: np.ndarray
    votes: np.ndarray
    hits: np.ndarray
    n_visible: np.ndarray
    confidence: np.ndarray
    floaters: np.ndarray
    label_ids: list[int]
    names: dict[int, str]
    options: FusionOptions = field(default_factory=FusionOptions)
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    # fusion.json's other entries (label-map scores, metrics) when read back by `load`; written again by `save`
    extra: dict = field(default_factory=dict, repr=False)

    __eq__ = dataclass_eq   # array-aware (splattwin.equality)

    def counts(self) -> dict[str, int]:
        return {self.names[k]: int((self.labels == k).sum()) for k in self.label_ids}

    def relabel(self, kappa: float) -> np.ndarray:
        """Consensus labels for another kappa from the final round's votes (no KNN smoothing)."""
        if self.votes is None or self.n_visible is None:
            raise ValueError("relabel needs the fusion's votes, which labels.npy / fusion.json do not keep "
                             "(a FusionResult.load): fuse again")
        return consensus(self.votes, self.n_visible, kappa, self.label_ids, self.options.min_views)[0]

    def save(self, out_dir: str | Path, extra: dict | None = None) -> Path:
        """`labels.npy` (int32 per Gaussian) + `fusion.json` (names, options, per-object counts, history,
        and `extra`: label-map scores, metrics), the only writer of both."""
        out_dir = Path(out_dir)
        io.write_npy(out_dir / "labels.npy", self.labels.astype(np.int32))
        io.write_json(out_dir / "fusion.json", {
            "objects": [{"name": self.names[k], "label": k, "n_gaussians": int((self.labels == k).sum())}
                        for k in self.label_ids],
            "n_gaussians": int(len(self.labels)), "options": self.options.__dict__,
            "history": self.history, "seconds": self.seconds, **self.extra, **(extra or {})})
        return out_dir

    @classmethod
    def load(cls, out_dir: str | Path) -> FusionResult:
        """A FusionResult back from what `save` wrote (labels.npy + fusion.json in `out_dir`): labels, names,
        label_ids, options, history, seconds, and fusion.json's other entries in `extra`. The per-view
        evidence (votes, hits, n_visible, confidence, floaters) is not saved: None."""
        from splattwin.limits import MAX_RECORD_BYTES, load_npy
        from splattwin.options import from_dict

        out_dir = Path(out_dir)
        meta_path, labels_path = out_dir / "fusion.json", out_dir / "labels.npy"
        meta = io.read_json(meta_path, "no fusion.json here: not a folder written by FusionResult.save "
                                       "(or splattwin fuse)", MAX_RECORD_BYTES)
        if not isinstance(meta, dict) or not isinstance(meta.get("objects"), list):
            raise InputError("malformed fusion.json: expected an object with an 'objects' list", meta_path)
        names: dict[int, str] = {}
        for o in meta["objects"]:
            lab = o.get("label") if isinstance(o, dict) else None
            if not isinstance(lab, int) or isinstance(lab, bool) or lab < 1 or not isinstance(o.get("name"), str):
                raise InputError(f"malformed fusion.json: each object needs a name and a label >= 1, got "
                                 f"{str(o)[:80]}", meta_path)
            names[lab] = o["name"]
        if not labels_path.is_file():
            raise InputError("no labels.npy beside fusion.json", labels_path)
        labels = load_npy(labels_path, "labels")
        if labels.ndim != 1 or labels.dtype.kind not in "iu":
            raise InputError(f"labels.npy must be one integer label per Gaussian, got {labels.dtype} {labels.shape}",
                             labels_path)
        n = meta.get("n_gaussians")
        if isinstance(n, int) and n != len(labels):
            raise InputError(f"labels.npy has {len(labels)} labels but fusion.json says {n} Gaussians", labels_path)
        opts = from_dict(FusionOptions, meta.get("options") or {}, meta_path)
        history = meta.get("history") if isinstance(meta.get("history"), list) else []
        seconds = meta.get("seconds") if isinstance(meta.get("seconds"), (int, float)) else 0.0
        extra = {k: v for k, v in meta.items()
                 if k not in ("objects", "n_gaussians", "options", "history", "seconds")}
        return cls(labels=labels.astype(np.int32), votes=None, hits=None, n_visible=None, confidence=None,
                   floaters=None, label_ids=list(names), names=names, options=opts, history=history,
                   seconds=float(seconds), extra=extra)


# -- algorithm steps (each unit-tested) -------------------------------------------------------

def dbscan_1d(z: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """Exact DBSCAN of 1-D values. z [n] -> cluster id [n] (0..K-1, -1 noise).

    Neighbourhoods are |z_a - z_b| <= eps including the point itself (scikit-learn's convention). A
    border point joins the cluster of its nearest core point.
    """
    z = np.asarray(z, dtype=np.float64)
    n = z.size
    out = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return out
    order = np.argsort(z, kind="stable")
    zs = z[order]
    lo = np.searchsorted(zs, zs - eps, side="left")
    hi = np.searchsorted(zs, zs + eps, side="right")
    core = (hi - lo) >= min_samples
    core_idx = np.flatnonzero(core)
    if core_idx.size == 0:
        return out
    zc = zs[core_idx]
    cid_core = np.concatenate([[0], np.cumsum(np.diff(zc) > eps)])
    # nearest core for every sorted point
    pos = np.searchsorted(zc, zs)
    left = np.clip(pos - 1, 0, zc.size - 1)
    right = np.clip(pos, 0, zc.size - 1)
    dl, dr = np.abs(zs - zc[left]), np.abs(zs - zc[right])
    near = np.where(dl <= dr, left, right)
    dist = np.minimum(dl, dr)
    cid = np.where(dist <= eps, cid_core[near], -1)
    out[order] = cid
    return out


def soft_gate(z: np.ndarray, eps: float = 0.02, min_samples: int = 10, sigma: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Depth-guided isolation weights for the in-mask visible Gaussians of one view and object.

    z [n] camera depths (m) -> (w [n] in [0,1], in_front [n] bool: gated-out points nearer than the
    main cluster). The largest DBSCAN cluster gets w = 1; others decay with their depth distance d to
    the largest cluster's interval as exp(-(d/sigma)^2). When DBSCAN finds no cluster (fewer than
    min_samples points) the mask cannot be checked and every point keeps w = 1.
    """
    z = np.asarray(z, dtype=np.float64)
    sigma = eps if sigma is None else sigma
    if z.size == 0:
        return np.ones(0), np.zeros(0, dtype=bool)
    cid = dbscan_1d(z, eps, min_samples)
    valid = cid >= 0
    if not valid.any():
        return np.ones(z.size), np.zeros(z.size, dtype=bool)
    sizes = np.bincount(cid[valid])
    main = int(np.argmax(sizes))
    zmain = z[cid == main]
    lo, hi = zmain.min(), zmain.max()
    d = np.maximum(lo - z, 0.0) + np.maximum(z - hi, 0.0)
    w = np.exp(-((d / sigma) ** 2))
    w[cid == main] = 1.0
    return w, (z < lo) & (w < 0.5)


def visible_mask(pix: np.ndarray, z: np.ndarray, depth: np.ndarray, tol: float = 0.02, tol_rel: float = 0.01
                 ) -> np.ndarray:
    """Visibility test. pix [N] (v*W+u, -1 outside), z [N] camera depth, depth [H,W] rendered (inf empty).

    True where the centre is inside the image and |z - depth(pixel)| <= tol + tol_rel * depth.
    """
    vis = pix >= 0
    d = depth.reshape(-1)[np.where(vis, pix, 0)]
    with np.errstate(invalid="ignore"):
        vis &= np.isfinite(d) & (np.abs(z - d) <= tol + tol_rel * np.where(np.isfinite(d), d, 0.0))
    return vis


def grazing(means: np.ndarray, normals: np.ndarray, center: np.ndarray, min_cos: float) -> np.ndarray:
    """[N] bool: splats whose normal makes |cos| < min_cos with the ray from `center` (nan normal -> False)."""
    d = means - center
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.abs((d * normals).sum(axis=1)) / np.linalg.norm(d, axis=1)
        return c < min_cos


def splat_normals(quats: np.ndarray, scales: np.ndarray, flatness: float = 0.3) -> np.ndarray:
    """[N,3] unit normals (axis of the smallest scale) of flat Gaussians, nan rows for the others.

    quats [N,4] wxyz, scales [N,3] m. Flat: smallest scale < flatness x the middle one.
    """
    R = matrix_from_quat_wxyz(quats)
    order = np.argsort(scales, axis=1)
    axis = order[:, 0]
    n = R[np.arange(len(R)), :, axis]
    s_sorted = np.take_along_axis(scales, order, axis=1)
    flat = s_sorted[:, 0] < flatness * s_sorted[:, 1]
    n[~flat] = np.nan
    return n


def consensus(votes: np.ndarray, n_visible: np.ndarray, kappa: float, label_ids: Sequence[int],
              min_views: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Weighted consensus with tau = N / kappa and conflict resolution by the largest vote.

    votes [N,L], n_visible [N] -> (labels [N] int32, confidence [N]): confidence is V/N of the chosen
    object, or 1 - max_o V_o/N for background (0 where never visible).
    """
    if kappa <= 0:
        raise InputError(f"kappa must be > 0, got {kappa}")
    n = n_visible.astype(np.float64)
    tau = n / kappa
    passes = (votes >= tau[:, None] - 1e-9) & (n[:, None] >= max(min_views, 1)) & (votes > 0)
    masked = np.where(passes, votes, -1.0)
    best = masked.argmax(axis=1) if votes.shape[1] else np.zeros(len(n), dtype=np.int64)
    has = passes.any(axis=1)
    ids = np.asarray(label_ids, dtype=np.int32)
    labels = np.where(has, ids[best] if len(ids) else 0, 0).astype(np.int32)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(n[:, None] > 0, votes / np.maximum(n[:, None], 1), 0.0)
    conf = np.where(has, ratio[np.arange(len(n)), best] if len(ids) else 0.0,
                    1.0 - (ratio.max(axis=1) if len(ids) else 0.0))
    conf = np.where(n > 0, conf, 0.0)
    return labels, np.clip(conf, 0.0, 1.0)


def view_observations(pix: np.ndarray, z: np.ndarray, vis: np.ndarray,
                      view_masks: Sequence[tuple[int, np.ndarray]], opts: FusionOptions
                      ) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Observation weights W_ij of one view (steps 2 and the vote of 3 in the module docstring).

    pix [N] pixel index (-1 outside), z [N] camera depth (m), vis [N] bool (`visible_mask`), view_masks:
    (column k, flat mask [H*W] bool) per object with a mask in this view. -> per object with at least
    one visible in-mask Gaussian: (k, idx [n] Gaussian indices, w [n] soft-gate weights, front [n] bool
    gated out in front of the object's main depth cluster)."""
    vis_idx = np.flatnonzero(vis)
    vpix = pix[vis_idx]
    out = []
    for k, m in view_masks:
        idx = vis_idx[m[vpix]]
        if idx.size == 0:
            continue
        w, front = soft_gate(z[idx], opts.eps, opts.min_samples, opts.gate_sigma)
        out.append((k, idx, w, front))
    return out


def smooth_labels(labels: np.ndarray, confidence: np.ndarray, neighbours, opts: FusionOptions
                  ) -> tuple[np.ndarray, int]:
    """Iterative KNN boundary refinement: `knn_smooth` passes (at most max(opts.iters, 1)) until fewer
    than opts.converge_share x N labels flip. Updates `confidence` of flipped points in place.
    -> (labels [N], total flips)."""
    flipped = 0
    for _ in range(max(opts.iters, 1)):
        labels, f = knn_smooth(labels, confidence, neighbours, opts.knn_threshold, opts.knn_confidence,
                               update_confidence=True)
        flipped += f
        if f < opts.converge_share * len(labels):
            break
    return labels, flipped


def find_floaters(labels: np.ndarray, gated_front: np.ndarray, hits: np.ndarray, share: float) -> np.ndarray:
    """[N] bool: background Gaussians gated out in front of an object (`soft_gate`'s `front`) in at least
    `share` of their in-mask visible observations (gated_front [N] counts, hits [N,L] observations)."""
    n_obs = hits.sum(axis=1)
    return (labels == 0) & (gated_front > 0) & (gated_front >= share * np.maximum(n_obs, 1))


class KnnCache:
    """k nearest other points of the Gaussian centres (scipy cKDTree), queried lazily and cached."""

    def __init__(self, means: np.ndarray, k: int):
        self.means = means
        self.k = max(0, min(k, len(means) - 1))
        self.tree = cKDTree(means) if self.k > 0 else None
        self.nb = np.full((len(means), self.k), -1, dtype=np.int64)

    def __call__(self, idx: np.ndarray) -> np.ndarray:
        """[M] point indices -> [M,k] neighbour indices."""
        if self.k == 0:
            return np.zeros((len(idx), 0), dtype=np.int64)
        todo = idx[self.nb[idx, 0] < 0]
        if todo.size:
            _, nb = self.tree.query(self.means[todo], k=self.k + 1, workers=2)
            self.nb[todo] = nb[:, 1:]
        return self.nb[idx]


def knn_smooth(labels: np.ndarray, confidence: np.ndarray, neighbours, threshold: float = 0.6,
               confidence_gate: float = 0.8, update_confidence: bool = False) -> tuple[np.ndarray, int]:
    """One KNN boundary-smoothing pass. -> (new labels [N], number changed).

    A label flips to its neighbours' majority label when that label holds >= threshold of the k
    neighbours and the point's own confidence is below confidence_gate (only those points are queried).
    neighbours: [N,k] indices, or a callable idx [M] -> [M,k] (e.g. `KnnCache`).
    update_confidence: write the neighbour share into `confidence` for flipped points (in place), so a
    later pass does not flip a well-supported point back.
    """
    idx = np.flatnonzero(confidence < confidence_gate)
    out = labels.copy()
    if idx.size == 0:
        return out, 0
    nb_idx = neighbours(idx) if callable(neighbours) else np.asarray(neighbours)[idx]
    if nb_idx.shape[1] == 0:
        return out, 0
    nb = labels[nb_idx]
    values = np.unique(labels)
    counts = np.stack([(nb == v).sum(axis=1) for v in values], axis=1)
    top = values[counts.argmax(axis=1)]
    share = counts.max(axis=1) / nb_idx.shape[1]
    flip = (share >= threshold) & (top != labels[idx])
    out[idx[flip]] = top[flip]
    if update_confidence:
        confidence[idx[flip]] = share[flip]
    return out, int(flip.sum())


# -- driver -----------------------------------------------------------------------------------

@dataclass
class View:
    """One fusion view: its name (mask set key) and camera."""

    name: str
    camera: Camera


def check_inputs(means, views, masks, normals=None) -> np.ndarray:
    """`means` as [N,3] float64, after checking the arguments of `fuse` / `naive_fusion` a library user
    passes (InputError naming the problem, instead of a wrong result or an IndexError deep inside)."""
    try:
        arr = np.asarray(means, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"fuse: means must be an [N,3] array of Gaussian centres: {e}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"fuse: means must be an [N,3] array of Gaussian centres, got shape {tuple(arr.shape)}"
                         + (" (transposed? pass means, not means.T)" if arr.ndim == 2 and arr.shape[0] == 3 else ""))
    if not np.all(np.isfinite(arr)):
        raise InputError(f"fuse: {int((~np.isfinite(arr)).any(axis=1).sum())} Gaussian centres are NaN or infinite")
    if isinstance(views, (str, bytes)) or not isinstance(views, Sequence):
        raise InputError(f"fuse: views must be a list of View(name, camera), got {type(views).__name__}")
    bad = [i for i, v in enumerate(views) if not isinstance(v, View)]
    if bad:
        got = type(views[bad[0]]).__name__
        raise InputError(f"fuse: views must be View(name, camera) objects (the name matching a mask view), got "
                         f"{got} at position {bad[0]}" + (": wrap cameras as View(frame.name, frame.camera)"
                                                          if got == "Camera" else ""))
    if not isinstance(masks, MaskSet):
        raise InputError(f"fuse: masks must be a MaskSet (splattwin.semantics.load_masks), got {type(masks).__name__}")
    if normals is not None and np.shape(normals) != arr.shape:
        raise InputError(f"fuse: normals must be [N,3] like means {tuple(arr.shape)}, got shape {np.shape(normals)}")
    return arr


def check_views(views: Sequence[View], masks: MaskSet, where: str | Path | None = None) -> list[int]:
    """Validate masks against the views' image sizes; returns the labels to fuse.

    Raises InputError for an empty mask set, size mismatches and objects seen in no fusion view. Mask
    views without a camera among `views` are not used.
    """
    sizes = {v.name: (v.camera.height, v.camera.width) for v in views}
    if not views:
        raise InputError("no views to fuse", where)
    if masks.masks and not any(k in sizes for k in masks.masks):   # else "empty mask set", though masks were given
        mine = sorted(masks.masks)
        raise InputError(f"no view has masks: the views are named {short_repr(sorted(sizes), 120)}, the mask set's "
                         f"views {short_repr(mine, 120)} (View(name, camera): the name is the mask view's, e.g. "
                         f"the image stem `Frame.name`)", where)
    sub = MaskSet(objects=dict(masks.objects), prompts=dict(masks.prompts),
                  masks={k: v for k, v in masks.masks.items() if k in sizes},
                  scores={k: v for k, v in masks.scores.items() if k in sizes},
                  sizes={k: v for k, v in masks.sizes.items() if k in sizes})
    sub.validate(sizes, where)
    return masks.labels


def fuse(means: np.ndarray, views: Sequence[View], masks: MaskSet, options: FusionOptions | None = None,
         depth_renderer: DepthRenderer | None = None, normals: np.ndarray | None = None,
         progress: bool = False) -> FusionResult:
    """Fuse 2D masks into per-Gaussian labels (algorithm in the module docstring).

    means [N,3] Gaussian centres (world, m). views: cameras named like the mask views.
    depth_renderer(keep [N] bool | None, cameras) -> list of [H,W] depth; default: `PointDepth(means)`
    (pass `SplatDepth(gaussians)` to use the rasterizer's expected depth).
    normals [N,3] unit normals of flat splats (nan rows for non-flat ones, see `splat_normals`): a splat
    seen at a grazing angle (|cos| < min_cos) sits on a silhouette, where the 2D mask boundary is a
    coin flip, so that view does not count for it (neither in N nor in the votes).
    """
    opts = options or FusionOptions()
    t0 = time.perf_counter()
    means = check_inputs(means, views, masks, normals)
    label_ids = check_views(views, masks)
    N, L = len(means), len(label_ids)
    renderer = depth_renderer or PointDepth(means)
    cams = [v.camera for v in views]
    # projections are fixed across rounds; share them with a point renderer of the same centres
    shared = isinstance(renderer, PointDepth) and renderer.means.shape == means.shape and np.array_equal(renderer.means, means)
    proj = [renderer.project(c) if shared else project_to_pixels(means, c) for c in cams]
    flat_masks = [[(k, m.reshape(-1)) for k, m in ((k, masks.get(v.name, lab)) for k, lab in enumerate(label_ids))
                   if m is not None] for v in views]
    neighbours = KnnCache(means, opts.knn_k)
    floaters = np.zeros(N, dtype=bool)
    labels = np.zeros(N, dtype=np.int32)
    history: list[dict] = []
    from splattwin.progress import Progress

    bar = Progress(max(opts.iters, 1), "fusion rounds", unit="round", enabled=progress)
    rendered_without: np.ndarray | None = None
    for it in range(max(opts.iters, 1)):
        if rendered_without is None:
            depths = renderer(None, cams)
            rendered_without = floaters.copy()
        elif not np.array_equal(rendered_without, floaters):
            # re-render only the views that see a newly removed floater; the others would not change
            removed = floaters & ~rendered_without
            redo = [j for j, (pix, _) in enumerate(proj) if (pix[removed] >= 0).any()]
            if redo:
                for j, d in zip(redo, renderer(~floaters, [cams[j] for j in redo])):
                    depths[j] = d
            rendered_without = floaters.copy()
        votes = np.zeros((N, L), dtype=np.float64)
        hits = np.zeros((N, L), dtype=np.int32)
        n_vis = np.zeros(N, dtype=np.int32)
        gated_front = np.zeros(N, dtype=np.int32)
        for (pix, z), depth, fm, cam in zip(proj, depths, flat_masks, cams):
            vis = visible_mask(pix, z, depth, opts.depth_tol, opts.depth_tol_rel)
            if normals is not None and opts.min_cos > 0:
                vis &= ~grazing(means, normals, cam.center, opts.min_cos)
            n_vis += vis
            for k, idx, w, front in view_observations(pix, z, vis, fm, opts):
                votes[idx, k] += w
                hits[idx, k] += 1
                gated_front[idx] += front
        new, conf = consensus(votes, n_vis, opts.kappa, label_ids, opts.min_views)
        new, flipped = smooth_labels(new, conf, neighbours, opts)
        changed = int((new != labels).sum()) if it else N
        labels = new
        new_floaters = find_floaters(labels, gated_front, hits, opts.floater_share)
        history.append({"round": it + 1, "changed": changed, "knn_flipped": flipped,
                        "floaters": int(new_floaters.sum()),
                        "per_object": {masks.objects[k]: int((labels == k).sum()) for k in label_ids}})
        log.debug("fusion round %d: %s", it + 1, history[-1])
        bar.update(1)
        if not (new_floaters & ~floaters).any():
            # the depth maps would not change: another round would repeat this one exactly
            if it + 1 < max(opts.iters, 1):
                bar.set_description(f"fusion rounds (converged after {it + 1})")
                bar.set_total(it + 1)   # "2/3 rounds done" read as unfinished
            break
        floaters = floaters | new_floaters
    bar.close()
    res = FusionResult(labels=labels, votes=votes.astype(np.float32), hits=hits, n_visible=n_vis,
                       confidence=conf.astype(np.float32), floaters=floaters, label_ids=list(label_ids),
                       names={k: masks.objects[k] for k in label_ids}, options=opts, history=history,
                       seconds=time.perf_counter() - t0)
    for k in label_ids:
        if not (labels == k).any():
            warnings.warn(MaskWarning(f"object {masks.objects[k]!r} got no Gaussians: its masks never agree with "
                                      f"the 3D model (kappa {opts.kappa}); check masks and camera poses"))
    return res


def naive_fusion(means: np.ndarray, views: Sequence[View], masks: MaskSet, fraction: float = 0.5) -> np.ndarray:
    """Baseline of the published code: label o when the centre falls inside o's mask in at least
    fraction x (number of views) views; no visibility, no isolation; conflicts by most votes. -> [N] int32."""
    means = check_inputs(means, views, masks)
    label_ids = check_views(views, masks)
    votes = np.zeros((len(means), len(label_ids)), dtype=np.int32)
    for v in views:
        pix, _ = project_to_pixels(means, v.camera)
        inside = pix >= 0
        for k, lab in enumerate(label_ids):
            m = masks.get(v.name, lab)
            if m is None:
                continue
            votes[inside, k] += m.reshape(-1)[pix[inside]]
    need = int(len(views) * fraction)
    best = votes.argmax(axis=1)
    ok = votes[np.arange(len(means)), best] >= max(need, 1)
    return np.where(ok, np.asarray(label_ids, dtype=np.int32)[best], 0).astype(np.int32)
