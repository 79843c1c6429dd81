"""pipeline stage: `splattwin build` — every stage in order, resumable (`runner`: stage keys, state).

Entry point: `splattwin.pipeline.build.build(out, BuildOptions(...))` (the name `build` is also the
module's, so it is not re-exported here)."""

from __future__ import annotations

import importlib

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"BuildOptions": "options", "check_inputs": "build", "Context": "runner", "run_stages": "runner"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        mod = _EXPORTS[name]
        return getattr(importlib.import_module(mod if mod.startswith("splattwin.") else f"splattwin.pipeline.{mod}"), name)
    raise AttributeError(f"module 'splattwin.pipeline' has no attribute {name!r}")
