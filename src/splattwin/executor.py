"""Where tasks run: a local process pool (default, no extra install) or a Ray cluster, behind one API.

    ex = make_executor(ExecutorOptions(executor="ray", ray_address="auto"))   # or the defaults: local
    ex.run([Job(key, fn, args, Resources(cpus=1))], on_done=lambda job, outcome: [...more jobs])
    ex.close()

`ExecutorOptions` is the one home of the flags that pick it (`--executor`, `--ray-address`,
`--max-retries`, `--workers`): the robot stage nests it (`RobotOptions.cluster`: where the trials run,
`splattwin plan`, `build --robot.cluster.*`), and so do `splattwin sweep` and `splattwin batch`
(`splattwin.cluster`). A shared module (no stage imported): the robot stage below and the cluster commands
above the pipeline both use it.

A `Job` is a plain module-level function and picklable arguments (Ray ships the function by reference,
so every node imports it from its own splattwin install). `run` keeps the jobs going, calls
`on_done(job, outcome)` in the driver as each one finishes (in completion order), and submits the jobs
that callback returns: that is how a batch chains a capture's training and the rest of its build, and
how a sweep starts a cell's trials as soon as its twin exists. A task that raises is an `Outcome` with
`ok=False` and the error text, never an exception in the driver.

Fault tolerance, both executors: a worker process that dies (killed, out of memory, a crash in a C
extension) has its task run again, up to `max_retries` times; an exception raised by the task itself is
not retried (it would fail the same way). Ray does this itself (`max_retries`, `retry_exceptions=False`);
the local pool rebuilds itself after a dead worker and resubmits the tasks that were in flight. Tasks
write their outputs atomically and skip finished work, so a retry continues and loses nothing.

Resources: Ray schedules by `Resources` (CPUs, GPUs), so training tasks land on GPU nodes and trials on
CPU nodes. The local pool runs `workers` processes regardless (one machine, no scheduler of its own).

We do not write a scheduler: Ray is the engine on a cluster (resources, retries, autoscaling via
KubeRay); `concurrent.futures` is the engine on one machine.
"""

from __future__ import annotations

import logging
import os
import signal
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor
from concurrent.futures import wait as futures_wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterable

from splattwin.errors import InputError
from splattwin.options import option

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
ADDRESS_ENV = "SPLATTWIN_RAY_ADDRESS"
# bounds of the count options: a local pool starts up to --workers processes at once, and a task whose
# worker keeps dying is re-run --max-retries times
MAX_WORKERS = 1024
MAX_RETRIES = 100


@dataclass
class ExecutorOptions:
    """Where a command's tasks run. None of these changes a result (trial outcomes depend only on their
    seeds), so none is part of a stage key."""

    executor: str | None = option(None, "where the tasks run: local (a process pool on this machine) or ray (a Ray "
                                  "cluster: pip install 'splattwin[ray]'; a local Ray instance unless an address "
                                  f"is given); none: local, or ray when --ray-address or ${ADDRESS_ENV} names a "
                                  "cluster", choices=EXECUTORS, aliases=("executor",), hashed=False)
    ray_address: str | None = option(None, "Ray cluster to run on: 'auto' (the cluster this node belongs to), "
                                     "HOST:6379 or ray://HOST:10001; implies --executor ray (none: "
                                     f"${ADDRESS_ENV}). Inputs and outputs must be on a filesystem every node "
                                     "mounts at the same path", aliases=("ray-address",), hashed=False)
    max_retries: int = option(3, f"times a task is run again after its worker process died (killed, out of memory, "
                              f"node lost; at most {MAX_RETRIES}); a task that raises is not retried", aliases=("max-retries",), hashed=False)
    workers: int | None = option(None, f"local: processes (at most {MAX_WORKERS}; none: as many tasks as fit the CPU count); ray without an "
                                 "address: CPUs of the local Ray instance (none: all)", aliases=("workers",),
                                 hashed=False)

    def resolve(self) -> tuple[str, str | None]:
        """(kind, address): an address (option or $SPLATTWIN_RAY_ADDRESS) means Ray unless executor is
        "local"; Ray without an address: a local Ray instance."""
        if self.executor is not None and self.executor not in EXECUTORS:
            raise InputError(f"unknown executor {self.executor!r} (choose from {', '.join(EXECUTORS)})")
        if not 0 <= self.max_retries <= MAX_RETRIES:
            raise InputError(f"--max-retries must be in [0, {MAX_RETRIES}], got {self.max_retries}")
        if self.workers is not None and not 1 <= self.workers <= MAX_WORKERS:
            raise InputError(f"--workers must be in [1, {MAX_WORKERS}], got {self.workers}")
        env = os.environ.get(ADDRESS_ENV) or None
        if self.executor == "local":
            if self.ray_address:
                raise InputError("--ray-address needs --executor ray (or no --executor)")
            return "local", None
        if self.executor == "ray" or self.ray_address or env:
            return "ray", self.ray_address or env
        return "local", None


DEFAULT_MAX_RETRIES = ExecutorOptions.max_retries


@dataclass(frozen=True)
class Resources:
    """What one task reserves on a Ray node: logical CPUs and GPUs (fractions allowed, as in Ray)."""

    cpus: float = 1.0
    gpus: float = 0.0


@dataclass
class Job:
    """One task: `fn(*args)` run in a worker. key: the caller's handle (any hashable); name: shown in
    Ray's process title and dashboard."""

    key: Hashable
    fn: Callable[..., Any]
    args: tuple = ()
    resources: Resources = field(default_factory=Resources)
    name: str | None = None


@dataclass
class Outcome:
    """How a job ended: ok with its return value, or not ok with the error text (the task raised, or its
    worker died more than max_retries times). attempts: 1 + the retries after dead workers (local pool;
    Ray retries inside and reports 1)."""

    ok: bool
    value: Any = None
    error: str | None = None
    attempts: int = 1


OnDone = Callable[[Job, Outcome], Iterable[Job] | None]


class Executor:
    """Base class: `submit` / `wait_any` / `outcome` per backend; `run` drives them (module docstring)."""

    kind = "base"

    def __init__(self, max_retries: int = DEFAULT_MAX_RETRIES):
        if max_retries < 0:
            raise InputError(f"--max-retries must be >= 0, got {max_retries}")
        self.max_retries = max_retries

    # -- backend API -----------------------------------------------------------------------------
    @property
    def workers(self) -> int:
        """How many 1-CPU tasks run at once."""
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError

    def submit(self, job: Job) -> Any:
        raise NotImplementedError

    def wait_any(self, handles: list, timeout: float | None = None) -> list:
        """The handles that finished (at least one unless the timeout passed)."""
        raise NotImplementedError

    def outcome(self, handle) -> Outcome | None:
        """The finished job's outcome, or None when it was resubmitted (its worker died)."""
        raise NotImplementedError

    def close(self, abort: bool = False) -> None:
        """Release the workers. abort: the command was stopped; ask the tasks in flight to stop too."""

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # stopped by Ctrl-C or SIGTERM (the CLI raises KeyboardInterrupt for both): the tasks in flight stop too
        self.close(abort=exc_type is not None and issubclass(exc_type, KeyboardInterrupt))

    # -- driver loop -------------------------------------------------------------------------------
    def run(self, jobs: Iterable[Job], on_done: OnDone | None = None, progress: bool = True,
            description: str = "tasks", total: int | None = None) -> dict[Hashable, Outcome]:
        """Run `jobs` (and whatever `on_done` returns for each finished one) to the end.

        Returns key -> Outcome of every job run. total: the expected number of jobs for the progress bar
        (default: those known so far)."""
        pending: dict[Any, Job] = {}
        outcomes: dict[Hashable, Outcome] = {}

        def add(new: Iterable[Job] | None) -> None:
            for j in new or ():
                pending[self.submit(j)] = j

        add(jobs)
        bar = _Bar(progress, description, total if total is not None else len(pending))
        try:
            while pending:
                for h in self.wait_any(list(pending), timeout=1.0):
                    out = self.outcome(h)
                    job = pending.pop(h)
                    if out is None:          # resubmitted after a dead worker: same job, new handle
                        continue
                    outcomes[job.key] = out
                    if not out.ok:
                        log.warning("task %s failed: %s", job.name or job.key, out.error)
                    more = list(on_done(job, out) or ()) if on_done is not None else []
                    add(more)
                    bar.advance(len(pending) + len(outcomes) if total is None else None)
                # handles resubmitted inside outcome() come back through _resubmitted
                for h, j in self._take_resubmitted():
                    pending[h] = j
        except BaseException:
            bar.close(failed=True)   # "stopped after", not "done in" (Ctrl-C, a lost cluster)
            raise
        bar.close()
        return outcomes

    def _take_resubmitted(self) -> list:
        return []


class _Bar:
    """Progress of the jobs (`splattwin.progress.Progress`: a bar with ETA, plain lines in a log; or nothing)."""

    def __init__(self, enabled: bool, description: str, total: int):
        from splattwin.progress import Progress

        self.p = Progress(total, description, unit="job", enabled=enabled and total > 0)

    def advance(self, new_total: int | None) -> None:
        if new_total is not None:
            self.p.set_total(new_total)
        self.p.update(1)

    def close(self, failed: bool = False) -> None:
        self.p.close(failed=failed)


def limit_threads(cpus: float) -> None:
    """Keep a task's thread pools (numba, torch) within the CPUs it reserved; Ray itself only sets
    OMP_NUM_THREADS. Called at the start of a task that computes in parallel."""
    n = max(1, int(cpus))
    try:
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    except Exception:  # numba missing or its threading layer already fixed: keep its default
        pass
    try:
        import torch

        torch.set_num_threads(n)
    except Exception:
        pass


# -- local process pool ------------------------------------------------------------------------------
def _call(fn: Callable, args: tuple) -> Any:
    return fn(*args)


PARENT_POLL_S = 0.5


STOP_SIGNAL = signal.SIGUSR1   # the pool's request to its workers: stop as on a Ctrl-C of their own


def _stop_as_interrupted(signum, frame) -> None:
    """A worker's handler of STOP_SIGNAL: the command was stopped (`LocalExecutor.close(abort=True)`); act as
    on the first Ctrl-C/SIGTERM (a training step finishes and saves, then the task stops), unless this
    worker already got one itself (a terminal's Ctrl-C reaches every process of the group): a second would
    stop it at once, losing the save."""
    from splattwin import interrupt

    if interrupt.stop_requested():
        return
    # the Python-level SIGTERM handler, called directly: a native library (Ray, pycolmap's glog) may hold the
    # signal itself at the C level and would end the process with a stack dump instead
    handler = signal.getsignal(signal.SIGTERM)
    if callable(handler):
        handler(signal.SIGTERM, frame)
    else:   # no handler of ours (a library caller's pool): stop the task as a Ctrl-C does
        raise KeyboardInterrupt


def _exit_with_parent(parent: int) -> None:
    """Pool worker initializer: exit when the process that started the pool is gone (`kill -9` of
    `plan`): an orphaned worker would go on writing trials into a folder nobody holds any more. And stop
    its task when the pool asks (STOP_SIGNAL: the command got SIGTERM, which reached it alone)."""
    import threading
    import time

    signal.signal(STOP_SIGNAL, _stop_as_interrupted)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="splattwin-parent-watch", daemon=True).start()


@dataclass(eq=False)
class _LocalHandle:
    job: Job
    future: Future
    attempt: int = 1


class LocalExecutor(Executor):
    """Tasks in a `ProcessPoolExecutor` of `workers` processes (default: CPU count) on this machine.

    A dead worker breaks a Python process pool for every task in flight: the pool is rebuilt and those
    tasks are resubmitted (each at most `max_retries` times)."""

    kind = "local"

    def __init__(self, workers: int | None = None, max_retries: int = DEFAULT_MAX_RETRIES):
        super().__init__(max_retries)
        if workers is not None and workers < 1:
            raise InputError(f"--workers must be >= 1, got {workers}")
        self._workers = workers or os.cpu_count() or 1
        self._pool: ProcessPoolExecutor | None = None
        self._resubmitted: list = []

    @property
    def workers(self) -> int:
        return self._workers

    def describe(self) -> str:
        return f"local process pool, {self._workers} worker{'s' if self._workers != 1 else ''}"

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self._workers, initializer=_exit_with_parent,
                                             initargs=(os.getpid(),))
        return self._pool

    def submit(self, job: Job, attempt: int = 1) -> _LocalHandle:
        try:
            fut = self._get_pool().submit(_call, job.fn, job.args)
        except BrokenProcessPool:
            self._restart()
            fut = self._get_pool().submit(_call, job.fn, job.args)
        return _LocalHandle(job, fut, attempt)

    def _restart(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = None

    def wait_any(self, handles: list, timeout: float | None = None) -> list:
        by_future = {h.future: h for h in handles}
        done, _ = futures_wait(list(by_future), timeout=timeout, return_when=FIRST_COMPLETED)
        return [by_future[f] for f in done]

    def outcome(self, handle: _LocalHandle) -> Outcome | None:
        try:
            return Outcome(True, handle.future.result(), attempts=handle.attempt)
        except BrokenProcessPool as e:
            if handle.attempt > self.max_retries:
                return Outcome(False, error=f"worker process died {handle.attempt} times ({e})", attempts=handle.attempt)
            if self._pool is not None and getattr(self._pool, "_broken", False):
                log.warning("a worker process died; restarting the pool and resubmitting its tasks")
                self._restart()
            self._resubmitted.append(self.submit(handle.job, handle.attempt + 1))
            return None
        except Exception as e:  # the task raised: not retried
            return Outcome(False, error=f"{type(e).__name__}: {e}", attempts=handle.attempt)

    def _take_resubmitted(self) -> list:
        out = [(h, h.job) for h in self._resubmitted]
        self._resubmitted = []
        return out

    def close(self, abort: bool = False) -> None:
        """Shut the pool down after its tasks. abort (the command got Ctrl-C or SIGTERM): queued tasks are
        cancelled and the running ones asked to stop (STOP_SIGNAL); before, a SIGTERM to the command (`kill`,
        `timeout`, a Kubernetes pod's stop) waited here for every running task to finish (a whole build)."""
        if self._pool is not None:
            if abort:
                for proc in list((getattr(self._pool, "_processes", None) or {}).values()):
                    try:
                        os.kill(proc.pid, STOP_SIGNAL)
                    except OSError:   # already gone
                        pass
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


# -- Ray -----------------------------------------------------------------------------------------------
def import_ray():
    """The ray module, or an InputError that says how to install it."""
    try:
        import ray
    except ImportError:
        raise InputError('--executor ray needs Ray: pip install "splattwin[ray]" (on every node of the cluster)') from None
    return ray


RAY_PORT, RAY_CLIENT_PORT = 6379, 10001   # Ray's default GCS port and Ray Client port
PROBE_TIMEOUT_S = 5.0


def check_reachable(address: str, timeout: float = PROBE_TIMEOUT_S) -> None:
    """Raise InputError when nothing accepts a TCP connection at a Ray address ("HOST:PORT", "ray://HOST:PORT";
    "auto" is left to Ray, which answers at once when it finds no cluster).

    Why: `ray.init(address=...)` with nobody listening there retries for about 12 minutes (20 attempts of
    ~36 s) while printing Ray's own warnings, so a mistyped address or a head node that is down looked hung."""
    import socket

    if address == "auto":
        return
    client = address.startswith("ray://")
    hostport = address[len("ray://"):] if client else address
    host, sep, port_text = hostport.rpartition(":")
    if not sep or "]" in port_text:   # no port given: Ray's default
        host, port_text = hostport, ""
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_text) if port_text else (RAY_CLIENT_PORT if client else RAY_PORT)
        if not 0 < port < 65536:
            raise ValueError(port)
    except ValueError:
        raise InputError(f"bad Ray address {address!r}: write HOST:PORT, ray://HOST:PORT or auto") from None
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as e:
        why = e.strerror or type(e).__name__   # "Connection refused", "timed out", a name that does not resolve
        raise InputError(f"no Ray cluster answers at {address!r} ({host}:{port}: {why}; from --ray-address or "
                         f"${ADDRESS_ENV}): start it there (`ray start --head`), check the address, or run "
                         "without an address (--executor local: this machine's process pool)") from None


class RayExecutor(Executor):
    """Tasks on a Ray cluster: `address` ("auto", "HOST:6379", "ray://HOST:10001"), or None to start a
    local Ray instance with `num_cpus` CPUs (default: all). When this process is already connected
    (`ray.init` called before), that session is used and left open on close."""

    kind = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None,
                 max_retries: int = DEFAULT_MAX_RETRIES):
        super().__init__(max_retries)
        ray = import_ray()
        self._ray = ray
        self._owned = False
        self.address = address
        if not ray.is_initialized():
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address:
                check_reachable(address)
                kw["address"] = address
            elif num_cpus is not None:
                kw["num_cpus"] = int(num_cpus)
            try:
                ray.init(**kw)
            except ConnectionError as e:
                raise InputError(f"cannot connect to the Ray cluster at {address!r}: {e}") from None
            self._owned = True
        self._remote: dict[Callable, Any] = {}

    @property
    def workers(self) -> int:
        return max(1, int(self._ray.cluster_resources().get("CPU", 1)))

    def gpus(self) -> float:
        """GPUs in the whole cluster (0 on a CPU-only cluster)."""
        return float(self._ray.cluster_resources().get("GPU", 0))

    def describe(self) -> str:
        res = self._ray.cluster_resources()
        nodes = sum(1 for n in self._ray.nodes() if n.get("Alive"))
        gpu = f", {res.get('GPU', 0):g} GPU" if res.get("GPU") else ""
        where = self.address or ("local instance" if self._owned else "connected session")
        return f"Ray ({where}): {nodes} node{'s' if nodes != 1 else ''}, {res.get('CPU', 0):g} CPU{gpu}"

    def submit(self, job: Job) -> Any:
        rf = self._remote.get(job.fn)
        if rf is None:
            rf = self._remote[job.fn] = self._ray.remote(job.fn)
        r = job.resources
        return rf.options(num_cpus=r.cpus, num_gpus=r.gpus, max_retries=self.max_retries, retry_exceptions=False,
                          name=job.name or job.fn.__name__).remote(*job.args)

    def wait_any(self, handles: list, timeout: float | None = None) -> list:
        ready, _ = self._ray.wait(handles, num_returns=1, timeout=timeout)
        if ready:  # everything else that is ready too, without waiting
            ready, _ = self._ray.wait(handles, num_returns=len(handles), timeout=0)
        return ready

    def outcome(self, handle) -> Outcome:
        ex = self._ray.exceptions
        try:
            return Outcome(True, self._ray.get(handle))
        except ex.RayTaskError as e:   # the task raised: its own exception, not Ray's wrapper
            cause = getattr(e, "cause", None)
            msg = f"{type(cause).__name__}: {cause}" if cause is not None else str(e).strip().splitlines()[-1]
            return Outcome(False, error=msg)
        except ex.RayError as e:       # worker/node died more than max_retries times, object lost, ...
            return Outcome(False, error=f"{type(e).__name__}: {str(e).strip().splitlines()[0][:300]}",
                           attempts=self.max_retries + 1)

    def close(self, abort: bool = False) -> None:
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()
        self._owned = False


def make_executor(options: ExecutorOptions | None = None, cpus_per_task: float = 1.0,
                  max_tasks: int | None = None) -> Executor:
    """The executor `options` ask for (the caller closes it; `with make_executor(...) as ex:`).

    Local pool: `options.workers` processes, by default as many `cpus_per_task`-CPU tasks as fit the CPU
    count, never more than `max_tasks`. Ray: `options.ray_address`, $SPLATTWIN_RAY_ADDRESS, or a local
    instance with `options.workers` CPUs."""
    options = options or ExecutorOptions()
    kind, address = options.resolve()
    if kind == "local":
        n = options.workers or max(1, int((os.cpu_count() or 1) // max(cpus_per_task, 1e-9)))
        if max_tasks is not None:
            n = max(1, min(n, max_tasks))
        return LocalExecutor(n, max_retries=options.max_retries)
    return RayExecutor(address, num_cpus=options.workers, max_retries=options.max_retries)
