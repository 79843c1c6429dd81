"""Stage runner with input hashing: finished stages are skipped, `--from STAGE` redoes from there,
and a killed run resumes without losing finished work.

Each stage declares what its result depends on, and its key is a SHA-256 over all of it:
- the options it reads (`option_keys`; values, not file names: a path option goes into `inputs`),
- the contents of the files and folders it reads (`inputs(ctx)` -> {name: path}: images, masks, poses,
  task YAML, robot poses...), hashed by `splattwin.hashing.DigestCache` (a size+mtime prefilter, so
  unchanged gigabytes cost a stat() each; the cache lives in TWIN/.splattwin/digests.json),
- its code: the source of the packages it runs (`code`) and of its stage function, so editing a
  stage's code re-runs it (a hand-set `version` can still force it),
- the keys of the stages it depends on (`deps`), so everything downstream of a change re-runs.
`--from STAGE` runs that stage and every later one again from scratch: they are named in `ctx.fresh`,
so a stage that resumes partial work of its own (training checkpoints) starts over instead (a finished
run's checkpoint would otherwise be "resumed" with nothing left to do: no retraining).
After a stage succeeds the runner records `{key, outputs, seconds, peak_rss_gib}` in
`TWIN/pipeline.json` (atomically; `splattwin plan` adds its own run's figures to the robot record under
"plan", `report.build.record_plan_run`, gone when the robot stage runs again); when a stage re-runs, its record and those of every later stage are
dropped first, so a run stopped midway never leaves a record of old outputs beside new ones. On the next run a stage whose recorded key matches and whose
outputs all exist (inside the twin folder) with the contents recorded (`digests`: a `splattwin plan` or
`report` run by hand since rewrote them, with other options) is skipped. twin.json's identity leaves out
what `splattwin export` rewrites on an unchanged twin (its timings, versions and export list:
`splattwin.hashing.output_digest`), so re-exporting does not redo the twin stage. Stages write their own outputs atomically, so a
kill leaves at most the unfinished stage to redo (and training resumes from its own checkpoint inside
the stage).
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
from splattwin.hashing import DIGEST_CACHE, DigestCache, changed_outputs, code_digest, output_digests
from splattwin.runtime import peak_rss_gib

log = logging.getLogger(__name__)

STATE_NAME = "pipeline.json"


@dataclass
class Stage:
    """One pipeline stage.

    run(ctx) -> dict of output name -> path (relative to the twin folder) or plain values.
    option_keys: the options (ctx.options keys, e.g. a stage's whole sub-config) its result depends on.
    deps: names of earlier stages whose results it consumes.
    inputs(ctx) -> {name: path or list of paths or None}: files/folders read from outside the stages'
        outputs (hashed by content when the key is computed, i.e. after the earlier stages ran).
    code: modules/packages whose source the stage runs (with the stage function: its code version).
    version: a hand-set extra version (rarely needed: the code digest changes with the code).
    """

    name: str
    run: Callable[["Context"], dict[str, Any]]
    option_keys: tuple[str, ...] = ()
    deps: tuple[str, ...] = ()
    version: str = "1"
    inputs: Callable[["Context"], dict[str, Any]] | None = None
    code: tuple[str, ...] = ()

    def code_version(self) -> str:
        return code_digest(self.code, [self.run])


@dataclass
class Context:
    """A run: the twin folder, the options as hashed into stage keys (`options`: {key: plain value}), the
    options object the stages read (`config`, e.g. BuildOptions), and what the stages returned."""

    out: Path
    options: dict[str, Any]
    results: dict[str, dict[str, Any]] = field(default_factory=dict)  # stage name -> its outputs
    timings: dict[str, float] = field(default_factory=dict)   # a skipped stage: the seconds it took when it ran
    peak_rss_gib: dict[str, float] = field(default_factory=dict)
    digests: DigestCache | None = None
    config: Any = None
    progress: bool = True
    fresh: set[str] = field(default_factory=set)   # stages redone on request (--from): start over, resume nothing
    skipped: list[str] = field(default_factory=list)   # stages found up to date and not run
    wall_s: float | None = None   # what this run took (None: not run by run_stages)

    def path(self, rel: str | Path) -> Path:
        return self.out / rel


def input_digests(stage: Stage, ctx: Context) -> dict[str, str]:
    """{input name: content digest} of the stage's declared inputs (see module docstring)."""
    if stage.inputs is None:
        return {}
    cache = ctx.digests if ctx.digests is not None else DigestCache()
    out = {}
    for name, p in (stage.inputs(ctx) or {}).items():
        if isinstance(p, bytes):  # data already in memory (e.g. a point cloud)
            out[name] = "bytes:" + hashlib.sha256(p).hexdigest()
        else:
            out[name] = cache.files(p) if isinstance(p, (list, tuple)) else cache.digest(p)
    return out


def stage_key(stage: Stage, options: dict[str, Any], dep_keys: dict[str, str],
              inputs: dict[str, str] | None = None) -> str:
    payload = {
        "stage": stage.name,
        "version": stage.version,
        "code": stage.code_version(),
        "options": {k: options.get(k) for k in stage.option_keys},
        "inputs": inputs or {},
        "deps": {d: dep_keys[d] for d in stage.deps},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def compute_keys(stages: list[Stage], ctx: Context) -> dict[str, str]:
    """Every stage's key as it would be computed now (inputs as they are on disk), without running
    anything: for inspection and tests."""
    if ctx.digests is None:
        ctx.digests = DigestCache()
    keys: dict[str, str] = {}
    for stage in stages:
        keys[stage.name] = stage_key(stage, ctx.options, keys, input_digests(stage, ctx))
    return keys


def _outputs_exist(out: Path, outputs: dict[str, Any]) -> bool:
    from splattwin.paths import is_inside

    if not isinstance(outputs, dict):
        return False
    for v in outputs.values():
        if isinstance(v, str) and v.startswith("@"):  # "@rel/path": a file the stage promises
            p = out / v[1:]
            if Path(v[1:]).is_absolute() or not is_inside(p, out) or not p.exists():
                return False
    return True


def load_state(out: Path) -> dict[str, Any]:
    p = out / STATE_NAME
    if not p.is_file():
        return {}
    state = io.read_record(p)
    if not isinstance(state, dict) or not all(isinstance(v, dict) for v in state.values()):
        log.warning("%s is corrupt; re-running all stages", p)
        return {}
    return state


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
    from splattwin.lock import prepare_output_dir

    t_start = time.perf_counter()
    prepare_output_dir(ctx.out)
    state = load_state(ctx.out)
    if ctx.digests is None:
        ctx.digests = DigestCache(ctx.out / DIGEST_CACHE)
    keys: dict[str, str] = {}
    redo = requested = False
    from splattwin.interrupt import check

    for stage in stages:
        check()   # a Ctrl-C that a library swallowed during the previous stage (trimesh's lazy imports)
        key = stage_key(stage, ctx.options, keys, input_digests(stage, ctx))
        ctx.digests.save()
        keys[stage.name] = key
        if stage.name == from_stage:
            redo = requested = True
        if requested:
            ctx.fresh.add(stage.name)
        rec = state.get(stage.name)
        changed = []
        if not redo and rec and rec.get("key") == key and _outputs_exist(ctx.out, rec.get("outputs", {})):
            changed = changed_outputs(ctx.out, rec, ctx.digests)
            if changed:
                log.info("%s: %s changed since this stage wrote it (a command run by hand?): running it again",
                         stage.name, ", ".join(changed))
        if not redo and not changed and rec and rec.get("key") == key and _outputs_exist(ctx.out, rec.get("outputs", {})):
            ctx.results[stage.name] = dict(rec["outputs"])
            ctx.timings[stage.name] = rec.get("seconds", 0.0)
            ctx.peak_rss_gib[stage.name] = rec.get("peak_rss_gib", 0.0)
            ctx.skipped.append(stage.name)
            if on_stage:
                on_stage(stage.name, "skip")
        else:
            redo = True  # everything downstream of a re-run stage re-runs too
            # ... so until each finishes, pipeline.json vouches for none of their old outputs: a run
            # stopped here (Ctrl-C, error) must not leave new poses recorded beside the old splats
            stale = [n for n in names[names.index(stage.name):] if n in state]
            if stale:
                for n in stale:
                    del state[n]
                io.write_json(ctx.out / STATE_NAME, state)
            if on_stage:
                on_stage(stage.name, "run")
            t0 = time.perf_counter()
            outputs = stage.run(ctx) or {}
            dt = time.perf_counter() - t0
            ctx.results[stage.name] = outputs
            ctx.timings[stage.name] = dt
            ctx.peak_rss_gib[stage.name] = peak_rss_gib()
            state[stage.name] = {"key": key, "outputs": outputs, "seconds": dt,
                                 "peak_rss_gib": ctx.peak_rss_gib[stage.name], "finished": time.time(),
                                 "digests": output_digests(ctx.out, outputs, ctx.digests)}
            ctx.digests.save()
            io.write_json(ctx.out / STATE_NAME, state)
            if on_stage:
                on_stage(stage.name, "done")
        if stage.name == until:
            break
    ctx.wall_s = time.perf_counter() - t_start
    return ctx
