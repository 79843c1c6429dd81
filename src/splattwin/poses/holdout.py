"""Held-out views: which views of a capture are kept out of training for the held-out PSNR/SSIM.

`select_heldout(names, options, own_split)` -> `Holdout` (the indices and a record of the rule);
`apply_holdout(dataset, options)` sets each frame's `split` in place. The rule (`HoldoutOptions`):
an explicit option wins (every K-th view, N views spread evenly, or listed views); otherwise a capture
with a split of its own keeps it; otherwise every 8th view starting with the first when there are at
least 6 views (Mip-NeRF 360 / 3DGS convention: views 0, 8, 16, ...), none below 6.

Views are counted in the capture's order (`Dataset.frames`), before pose estimation: the split of a
capture does not change with which images SfM registers (an unregistered held-out view is dropped).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from splattwin.errors import InputError
from splattwin.heldout import default_heldout
from splattwin.poses.options import HoldoutOptions
from splattwin.wording import ordinal, plural

log = logging.getLogger(__name__)

HOLDOUT_KEY = "heldout"   # transforms.json / metrics.json key of the record


@dataclass
class Holdout:
    """indices: held-out positions in the view list (None: keep the capture's own split).
    source: "option" | "default" | "capture". rule: one line for people (report, logs)."""

    indices: list[int] | None
    source: str
    rule: str
    every: int | None = None
    names: list[str] = field(default_factory=list)

    def record(self) -> dict:
        """What transforms.json / metrics.json store."""
        out = {"source": self.source, "rule": self.rule, "views": list(self.names)}
        if self.every is not None:
            out["every"] = self.every
        return out


def _given(options: HoldoutOptions) -> list[str]:
    return [k for k in ("heldout_every", "heldout", "heldout_views") if getattr(options, k) is not None]


def _every(n: int, k: int) -> list[int]:
    return list(range(0, n, k))


def _spread(n: int, count: int) -> list[int]:
    """`count` positions evenly over n views, the first included (count = n // 8 gives every 8th view)."""
    return sorted({min(n - 1, int(i * n / count)) for i in range(count)})


def _listed(names: list[str], text: str) -> list[int]:
    by_name: dict[str, int] = {}
    for i, n in enumerate(names):
        by_name.setdefault(n, i)
    out = []
    for tok in (t.strip() for t in str(text).split(",")):
        if not tok:
            continue
        if tok.lstrip("-").isdigit():
            i = int(tok)
            if not 0 <= i < len(names):
                raise InputError(f"--heldout-views: view index {i} is out of range (the capture has {len(names)} "
                                 f"views, indices 0..{len(names) - 1})")
            out.append(i)
            continue
        stem = tok.rsplit("/", 1)[-1]
        stem = stem.rsplit(".", 1)[0] if stem not in by_name else stem
        if stem not in by_name:
            raise InputError(f"--heldout-views: no view named {tok!r} (views: {', '.join(names[:6])}"
                             f"{', ...' if len(names) > 6 else ''})")
        out.append(by_name[stem])
    if not out:
        raise InputError(f"--heldout-views {text!r}: give view indices or image names separated by commas")
    return sorted(set(out))


def select_heldout(names: list[str], options: HoldoutOptions | None = None, own_split: bool = False) -> Holdout:
    """The held-out views of a capture whose views are `names` (in capture order). own_split: the capture
    comes with a split of its own (kept unless an option is given). InputError for contradictory or
    impossible options (more than one given, K = 1, all views held out, unknown names)."""
    o = options or HoldoutOptions()
    n = len(names)
    given = _given(o)
    if len(given) > 1:
        raise InputError("give at most one of --heldout-every, --heldout and --heldout-views (got "
                         + ", ".join("--" + g.replace("_", "-") for g in given) + ")")
    every = None
    if o.heldout_every is not None:
        k = int(o.heldout_every)
        if k < 0 or k == 1:
            raise InputError(f"--heldout-every must be 0 (no held-out views) or at least 2, got {k}")
        idx, src, every = (_every(n, k) if k else []), "option", (k or None)
        rule = f"every {ordinal(k)} view from the first (--heldout-every {k})" if k else "none (--heldout-every 0)"
    elif o.heldout is not None:
        c = int(o.heldout)
        if c < 0:
            raise InputError(f"--heldout must be a count >= 0, got {c}")
        if c >= n and c > 0:
            raise InputError(f"--heldout {c}: the capture has only {n} views; at least one must stay for training")
        idx, src = (_spread(n, c) if c else []), "option"
        rule = f"{plural(c, 'view')} spread evenly from the first (--heldout {c})" if c else "none (--heldout 0)"
    elif o.heldout_views is not None:
        idx, src, rule = _listed(names, o.heldout_views), "option", f"listed views (--heldout-views {o.heldout_views})"
    elif own_split:
        return Holdout(None, "capture", "the capture's own split")
    else:   # the default rule (splattwin.heldout, shared with `capture info`)
        (idx, every, rule), src = default_heldout(n), "default"
    if n and len(idx) >= n:
        raise InputError(f"the hold-out ({rule}) leaves no view for training ({n} views)")
    return Holdout(idx, src, rule, every, [names[i] for i in idx])


def has_own_split(dataset) -> bool:
    """True when the dataset's file carries a train/held-out split (`Dataset.meta["split"]`)."""
    return bool(dataset.meta.get("split"))


def apply_holdout(dataset, options: HoldoutOptions | None = None) -> Holdout:
    """Set `split` of every frame of `dataset` (in place) by `select_heldout`; record the rule in
    `dataset.meta["heldout"]` and return it. A capture that keeps its own split is left as it is."""
    names = [f.name for f in dataset.frames]
    h = select_heldout(names, options, own_split=has_own_split(dataset))
    if h.indices is None:
        h.names = [f.name for f in dataset.frames if f.split == "heldout"]
        prior = dataset.meta.get(HOLDOUT_KEY)
        if isinstance(prior, dict) and isinstance(prior.get("rule"), str):
            h.rule, h.source = prior["rule"][:200], str(prior.get("source", "capture"))[:20]
            h.every = prior.get("every") if isinstance(prior.get("every"), int) else None
    else:
        held = set(h.indices)
        for i, f in enumerate(dataset.frames):
            f.split = "heldout" if i in held else "train"
    dataset.meta[HOLDOUT_KEY] = h.record()
    dataset.meta["split"] = True
    if h.names:
        log.info("held-out views (%s): %s", h.rule, ", ".join(h.names))
    else:
        log.info("no held-out views (%s)", h.rule)
    return h
