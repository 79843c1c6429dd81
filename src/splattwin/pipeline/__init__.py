"""pipeline stage: `splattwin build` — every stage in order, resumable (`runner`: stage keys, state).

Entry point: `splattwin.pipeline.build.build(out, BuildOptions(...))` (the name `build` is also the
module's, so it is not re-exported here)."""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"BuildOptions": "options", "check_inputs": "build", "Context": "runner", "run_stages": "runner"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
