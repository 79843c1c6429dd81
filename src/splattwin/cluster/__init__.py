"""Beyond one machine: parameter sweeps and batches of captures on an executor — a local process pool
(default) or a Ray cluster (`pip install "splattwin[ray]"`). Sits above the pipeline (a batch runs
`pipeline.build.build` per capture); nothing but the CLI imports it.

- `sweep`: `splattwin sweep TWIN` — a grid over fusion, geometry cleaning and trial parameters.
- `batch`: `splattwin batch CAPTURE... --out DIR` — one `build` per capture, one summary.
- `params`: the mapping of sweep parameters onto the stages' options dataclasses, by field name.
- `options`: `SweepOptions`, `BatchOptions` (the commands' own options; flags generated from them).

The executor itself (`Executor`, `LocalExecutor`, `RayExecutor`, `ExecutorOptions`, `make_executor`) is
the shared module `splattwin.executor`: the robot stage's trials (`splattwin plan --trials N`) run on it too.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"run_sweep": "sweep", "run_batch": "batch", "SweepOptions": "options", "BatchOptions": "options"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
