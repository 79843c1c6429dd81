"""Beyond one machine: trials, parameter sweeps and batches of captures on an executor — a local process
pool (default) or a Ray cluster (`pip install "splattwin[ray]"`).

- `executor`: `Executor` (`LocalExecutor`, `RayExecutor`, `make_executor`), `Job`, `Resources`, `Outcome`.
- `sweep`: `splattwin sweep TWIN` — a grid over fusion, geometry cleaning and trial parameters.
- `batch`: `splattwin batch CAPTURE... --out DIR` — one `build` per capture, one summary.
- `params`: the mapping of sweep parameters onto the stages' options objects, by field name.

Robot trials (`splattwin plan --trials N`) take an executor too: `robot.trials.run_trials(..., executor=)`.
"""

from splattwin.cluster.executor import (Executor, Job, LocalExecutor, Outcome, RayExecutor, Resources,
                                        make_executor)

__all__ = ["Executor", "Job", "LocalExecutor", "Outcome", "RayExecutor", "Resources", "make_executor"]
