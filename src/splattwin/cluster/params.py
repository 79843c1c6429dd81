"""Sweep parameters → the options objects of the stages they change, by field name.

The one mapping a sweep depends on: a parameter "TARGET.FIELD" sets FIELD of TARGET's options object,

    fusion.FIELD    → splattwin.semantics.options.FusionOptions  (kappa, iters, depth_tol, eps, ...)
    geometry.FIELD  → splattwin.geometry.options.GeometryOptions (cleaning: min_opacity, dbscan_eps, ...)
    trials.FIELD    → splattwin.robot.options.RobotOptions       (sigma, sigma_yaw, planner, in_hand)

and the CLI's short names are aliases (`--kappa` = fusion.kappa, `--fusion-iters` = fusion.iters,
`--sigma` = trials.sigma). Values are parsed by the field's declared type and checked by its choices
(`splattwin.options.specs`: the same declaration the stages' flags come from). When a stage's options
move, only `_targets` changes.
"""

from __future__ import annotations

import math
from dataclasses import MISSING
from typing import Any

from splattwin.errors import InputError
from splattwin.options import Spec, specs


def _targets() -> dict[str, tuple[type, frozenset[str] | None]]:
    """target -> (options class, the fields a sweep may set; None: all)."""
    from splattwin.geometry.options import GeometryOptions
    from splattwin.robot.options import RobotOptions
    from splattwin.semantics.options import FusionOptions

    return {"fusion": (FusionOptions, None),
            "geometry": (GeometryOptions, frozenset(s.name for s in specs(GeometryOptions))
                         - {"alpha_factors", "seed", "f1_threshold"}),
            "trials": (RobotOptions, frozenset({"sigma", "sigma_yaw", "planner", "in_hand"}))}


TARGETS = ("fusion", "geometry", "trials")   # in pipeline order: a fusion change re-runs geometry and trials
ALIASES = {"kappa": "fusion.kappa", "fusion_iters": "fusion.iters", "sigma": "trials.sigma",
           "sigma_yaw": "trials.sigma_yaw"}
# value checks beyond the type (a bad value fails before any task starts)
_RANGES = {"fusion.kappa": (1e-6, 100.0), "fusion.iters": (1, 20), "trials.sigma": (0.0, 0.05),
           "trials.sigma_yaw": (0.0, 0.5),
           # DBSCAN's eps and min_samples (scikit-learn refuses 0 inside the task)
           "fusion.eps": (1e-6, 10.0), "fusion.min_samples": (1, 100_000),
           "geometry.dbscan_eps": (1e-6, 10.0), "geometry.dbscan_min_samples": (1, 100_000)}
# shares, opacities and ratios
_RANGES.update({n: (0.0, 1.0) for n in (
    "fusion.min_cos", "fusion.knn_threshold", "fusion.knn_confidence", "fusion.floater_share", "fusion.converge_share",
    "geometry.min_opacity", "geometry.rejoin_precision", "geometry.surface_level", "geometry.min_coverage",
    "geometry.convex_ratio")})
# every other number of fusion and geometry is a length, count, ratio or threshold: never negative (before,
# `--clean min_opacity=-1` ran every cell and `geometry.dbscan_eps=-0.01` failed inside each task)
NON_NEGATIVE_TARGETS = ("fusion", "geometry")


def canonical(name: str) -> str:
    """'kappa' -> 'fusion.kappa'; 'geometry.min_opacity' stays; unknown names raise InputError."""
    name = name.strip().replace("-", "_")
    name = ALIASES.get(name, name)
    target, _, fld = name.partition(".")
    targets = _targets()
    if target not in targets or not fld:
        raise InputError(f"unknown sweep parameter {name!r}: use TARGET.FIELD with TARGET one of "
                         f"{', '.join(TARGETS)} (or {', '.join(ALIASES)})")
    cls, allowed = targets[target]
    names = {s.name for s in specs(cls)}
    if fld not in names or (allowed is not None and fld not in allowed):
        ok = sorted(allowed if allowed is not None else names)
        raise InputError(f"{cls.__name__} has no sweepable field {fld!r} (have: {', '.join(ok)})")
    return f"{target}.{fld}"


def _field(name: str) -> Spec:
    target, fld = name.split(".", 1)
    cls, _ = _targets()[target]
    return next(s for s in specs(cls) if s.name == fld)


def parse_value(name: str, text: str) -> Any:
    """One value of parameter `name` from text, by the field's declared type and choices."""
    spec = _field(name)
    b = spec.base
    tname = getattr(b, "__name__", str(b)) + (" or none" if spec.optional else "")
    t = text.strip()
    if spec.optional and t.lower() in ("none", "null", "auto"):
        return None
    try:
        if b is bool:
            if t.lower() in ("1", "true", "yes", "on"):
                return True
            if t.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(t)
        if b is int:
            v: Any = int(t)
        elif b is float:
            v = float(t)
            if not math.isfinite(v):
                raise ValueError(t)
        elif b is str:
            v = t
        else:
            raise InputError(f"sweep parameter {name} has type {tname}, which a sweep cannot set")
    except ValueError:
        raise InputError(f"bad value {text!r} for sweep parameter {name} (type {tname})") from None
    choices = spec.meta.get("choices")
    if choices and v not in choices:
        raise InputError(f"sweep parameter {name}: {v!r} is not one of {', '.join(map(str, choices))}")
    lo_hi = _RANGES.get(name)
    if lo_hi is not None and not lo_hi[0] <= v <= lo_hi[1]:
        raise InputError(f"sweep parameter {name} must be in [{lo_hi[0]:g}, {lo_hi[1]:g}], got {v}")
    if b in (int, float) and name.split(".")[0] in NON_NEGATIVE_TARGETS and v < 0:
        raise InputError(f"sweep parameter {name} must be >= 0, got {v}")
    return v


def parse_assignment(text: str) -> tuple[str, list]:
    """'NAME=V1,V2,...' -> (canonical name, [values])."""
    name, eq, values = text.partition("=")
    if not eq or not values.strip():
        raise InputError(f"sweep parameter {text!r}: write NAME=V1,V2,... (e.g. geometry.min_opacity=0.05,0.1)")
    name = canonical(name)
    return name, parse_values(name, values)


def parse_values(name: str, values: str) -> list:
    out = [parse_value(name, v) for v in values.split(",") if v.strip()]
    if not out:
        raise InputError(f"sweep parameter {name}: no values")
    if len(set(map(repr, out))) != len(out):
        raise InputError(f"sweep parameter {name}: repeated values {values!r}")
    return out


def split(params: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """{'fusion.kappa': 1.2, 'trials.sigma': 0.005} -> {'fusion': {'kappa': 1.2}, 'geometry': {}, 'trials': {...}}."""
    out: dict[str, dict[str, Any]] = {t: {} for t in TARGETS}
    for k, v in params.items():
        t, f = canonical(k).split(".", 1)
        out[t][f] = v
    return out


def apply(obj, values: dict[str, Any]):
    """A copy of the options object `obj` with `values` (field name -> value) set."""
    from dataclasses import replace

    return replace(obj, **values) if values else obj


def default(name: str) -> Any:
    """The default of the parameter's field, from its dataclass (never written here again)."""
    d = _field(name).default()
    return None if d is MISSING else d
