"""Stage runner with input hashing: finished stages are skipped, `--from STAGE` redoes from there,
and a killed run resumes without losing finished work.

Each stage declares which options it depends on. Its key is a SHA-256 over those options, the keys of
the stages it depends on and the stage's code version. After a stage succeeds the runner records
`{key, outputs, seconds, peak_rss_gib}` in `TWIN/pipeline.json` (atomically). On the next run a stage
whose recorded key matches and whose outputs all exist is skipped. Stages write their own outputs
atomically, so a kill leaves at most the unfinished stage to redo (and training resumes from its own
checkpoint inside the stage).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from splattwin import io
from splattwin.errors import InputError

log = logging.getLogger(__name__)

STATE_NAME = "pipeline.json"


@dataclass
class Stage:
    """One pipeline stage.

    run(ctx) -> dict of output name -> path (relative to the twin folder) or plain values.
    option_keys: the options (ctx.options keys) this stage's result depends on.
    deps: names of earlier stages whose results it consumes.
    """

    name: str
    run: Callable[["Context"], dict[str, Any]]
    option_keys: tuple[str, ...] = ()
    deps: tuple[str, ...] = ()
    version: str = "1"


@dataclass
class Context:
    out: Path
    options: dict[str, Any]
    results: dict[str, dict[str, Any]] = field(default_factory=dict)  # stage name -> its outputs
    timings: dict[str, float] = field(default_factory=dict)
    peak_rss_gib: dict[str, float] = field(default_factory=dict)

    def path(self, rel: str | Path) -> Path:
        return self.out / rel


def _peak_rss_gib() -> float:
    import resource

    # ru_maxrss is in KiB on Linux; counts this process and waited-for children.
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return r / (1024 ** 2)


def stage_key(stage: Stage, options: dict[str, Any], dep_keys: dict[str, str]) -> str:
    payload = {
        "stage": stage.name,
        "version": stage.version,
        "options": {k: options.get(k) for k in stage.option_keys},
        "deps": {d: dep_keys[d] for d in stage.deps},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _outputs_exist(out: Path, outputs: dict[str, Any]) -> bool:
    for v in outputs.values():
        if isinstance(v, str) and v.startswith("@"):  # "@rel/path": a file the stage promises
            if not (out / v[1:]).exists():
                return False
    return True


def load_state(out: Path) -> dict[str, Any]:
    p = out / STATE_NAME
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError:
        log.warning("%s is corrupt; re-running all stages", p)
        return {}


def run_stages(stages: list[Stage], ctx: Context, from_stage: str | None = None,
               until: str | None = None, on_stage: Callable[[str, str], None] | None = None) -> Context:
    """Run `stages` in order; skip those whose key matches the recorded state (see module docstring).

    on_stage(name, status) is called with status "skip" | "run" | "done".
    """
    names = [s.name for s in stages]
    if from_stage is not None and from_stage not in names:
        raise InputError(f"--from: unknown stage {from_stage!r} (stages: {', '.join(names)})")
    if until is not None and until not in names:
        raise InputError(f"--until: unknown stage {until!r} (stages: {', '.join(names)})")
    ctx.out.mkdir(parents=True, exist_ok=True)
    state = load_state(ctx.out)
    keys: dict[str, str] = {}
    redo = False
    for stage in stages:
        key = stage_key(stage, ctx.options, keys)
        keys[stage.name] = key
        if stage.name == from_stage:
            redo = True
        rec = state.get(stage.name)
        if not redo and rec and rec.get("key") == key and _outputs_exist(ctx.out, rec.get("outputs", {})):
            ctx.results[stage.name] = rec["outputs"]
            ctx.timings[stage.name] = rec.get("seconds", 0.0)
            ctx.peak_rss_gib[stage.name] = rec.get("peak_rss_gib", 0.0)
            if on_stage:
                on_stage(stage.name, "skip")
        else:
            redo = True  # everything downstream of a re-run stage re-runs too
            if on_stage:
                on_stage(stage.name, "run")
            t0 = time.perf_counter()
            outputs = stage.run(ctx) or {}
            dt = time.perf_counter() - t0
            ctx.results[stage.name] = outputs
            ctx.timings[stage.name] = dt
            ctx.peak_rss_gib[stage.name] = _peak_rss_gib()
            state[stage.name] = {"key": key, "outputs": outputs, "seconds": dt,
                                 "peak_rss_gib": ctx.peak_rss_gib[stage.name], "finished": time.time()}
            io.write_json(ctx.out / STATE_NAME, state)
            if on_stage:
                on_stage(stage.name, "done")
        if stage.name == until:
            break
    return ctx
