"""Executors: local process pool and Ray run the same jobs with the same outcomes; a task that raises is
reported (not retried); a worker process that dies has its task run again (max_retries)."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

from splattwin.executor import ExecutorOptions, Job, LocalExecutor, RayExecutor, Resources, make_executor
from splattwin.errors import InputError


def _square(x: int) -> int:
    return x * x


def _fail(x: int) -> int:
    raise ValueError(f"bad value {x}")


def _die_once(marker: str) -> int:
    """Kill the own worker process the first time (marker file absent); return the PID when it survives."""
    if not Path(marker).exists():
        Path(marker).write_text("died")
        os.kill(os.getpid(), signal.SIGKILL)
    return os.getpid()


def _always_die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


@pytest.fixture(scope="module", autouse=True)
def _by_value():
    """Ray workers cannot import this test module by name: ship its functions by value."""
    import ray.cloudpickle

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.fixture(params=["local", "ray"])
def executor(request, ray_session):
    ex = LocalExecutor(2, max_retries=2) if request.param == "local" else RayExecutor(max_retries=2)
    yield ex
    ex.close()


def test_jobs_chained_and_failures_reported(executor):
    """on_done's returned jobs run too; a raising task is an Outcome with its error, run once."""
    seen = []

    def on_done(job, out):
        seen.append(job.key)
        if job.key[0] == "sq" and job.key[1] < 3:
            return [Job(("chain", job.key[1]), _square, (out.value,))]
        return []

    jobs = [Job(("sq", i), _square, (i,), Resources(cpus=1)) for i in range(4)] + [Job(("bad", 0), _fail, (7,))]
    res = executor.run(jobs, on_done=on_done, progress=False)
    assert {k: o.value for k, o in res.items() if o.ok} == {("sq", 0): 0, ("sq", 1): 1, ("sq", 2): 4, ("sq", 3): 9,
                                                           ("chain", 0): 0, ("chain", 1): 1, ("chain", 2): 16}
    bad = res[("bad", 0)]
    assert not bad.ok and bad.error == "ValueError: bad value 7" and bad.attempts == 1
    assert sorted(seen) == sorted(res)   # every finished job went through on_done exactly once


def test_dead_worker_is_retried(executor, tmp_path):
    marker = tmp_path / "died"
    res = executor.run([Job("die", _die_once, (str(marker),)), Job("sq", _square, (5,))], progress=False)
    assert marker.is_file(), "the task did not kill its worker"
    assert res["die"].ok and res["die"].value != os.getpid()   # ran again in a new worker process
    assert res["sq"].ok and res["sq"].value == 25              # a task beside it is not lost either
    if executor.kind == "local":
        assert res["die"].attempts == 2


def test_worker_dying_every_time_fails_after_max_retries(executor):
    res = executor.run([Job("die", _always_die)], progress=False)
    assert not res["die"].ok and res["die"].attempts == 3
    assert "died" in res["die"].error or "Crashed" in res["die"].error


def test_make_executor_errors(monkeypatch):
    monkeypatch.delenv("SPLATTWIN_RAY_ADDRESS", raising=False)
    with pytest.raises(InputError, match="unknown executor"):
        make_executor(ExecutorOptions(executor="slurm"))
    with pytest.raises(InputError, match="--ray-address needs --executor ray"):
        make_executor(ExecutorOptions(executor="local", ray_address="auto"))
    with pytest.raises(InputError, match="--workers"):
        make_executor(ExecutorOptions(workers=0))
    with pytest.raises(InputError, match="--max-retries"):
        make_executor(ExecutorOptions(max_retries=-1))
    assert make_executor(ExecutorOptions(workers=3)).workers == 3
    # the default pool: as many tasks as fit the CPUs, never more than there are tasks
    assert make_executor(cpus_per_task=1.0).workers == (os.cpu_count() or 1)
    assert make_executor(max_tasks=1).workers == 1
    assert make_executor(cpus_per_task=1e6).workers == 1


def test_ray_executor_uses_the_open_session(ray_session):
    """With ray.init done before (a notebook, a test session), the executor runs there and leaves it open."""
    ex = RayExecutor()
    assert ex.workers == 2 and "Ray" in ex.describe()
    ex.close()
    assert ray_session.is_initialized()


def test_ray_missing_is_a_clear_input_error(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **kw):
        if name == "ray":
            raise ImportError("no ray")
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(InputError, match=r"splattwin\[ray\]"):
        make_executor(ExecutorOptions(executor="ray"))


def test_executor_choice_from_options_and_environment(monkeypatch):
    monkeypatch.delenv("SPLATTWIN_RAY_ADDRESS", raising=False)
    E = ExecutorOptions
    assert E().resolve() == ("local", None)                                 # the default needs no Ray
    assert E(executor="ray").resolve() == ("ray", None)                     # a local Ray instance
    assert E(ray_address="auto").resolve() == ("ray", "auto")               # an address means Ray
    monkeypatch.setenv("SPLATTWIN_RAY_ADDRESS", "head:6379")
    assert E().resolve() == ("ray", "head:6379")
    assert E(executor="ray", ray_address="other:6379").resolve() == ("ray", "other:6379")  # the option wins
    assert E(executor="local").resolve() == ("local", None)                 # local still runs locally


def test_executor_flags_are_generated_once_and_change_no_key():
    """`plan --executor/--ray-address/--max-retries/--workers` are the generated flags of
    RobotOptions.cluster (also `--cluster.*`; `build --robot.cluster.*`); the robot stage's key ignores them."""
    from splattwin.cli import build_parser
    from splattwin.options import from_args, to_dict
    from splattwin.pipeline.cli import resolve_options
    from splattwin.robot.options import RobotOptions

    p = build_parser()
    a = p.parse_args(["plan", "twin", "--executor", "ray", "--ray-address", "h:6379", "--max-retries", "5",
                      "--workers", "4", "--trials", "3"])
    o = from_args(RobotOptions, a)
    assert o.cluster == ExecutorOptions(executor="ray", ray_address="h:6379", max_retries=5, workers=4)
    assert from_args(RobotOptions, p.parse_args(["plan", "twin", "--cluster.max-retries", "1"])).cluster.max_retries == 1
    assert to_dict(o, "key") == to_dict(RobotOptions(trials=3), "key")
    b = resolve_options(p.parse_args(["build", "in", "--out", "t", "--robot.cluster.executor", "local"]))
    assert b.robot.cluster.executor == "local"
    assert "cluster" not in to_dict(b, "key")["robot"]
    with pytest.raises(SystemExit):
        p.parse_args(["plan", "twin", "--executor", "slurm"])


def test_an_interrupted_run_s_progress_says_stopped_not_done(capsys):
    """Ctrl-C while the trials run printed "trials ...: 0/3 job done in 1 s"."""
    def interrupt(job, out):
        raise KeyboardInterrupt

    with LocalExecutor(workers=1) as ex:
        with pytest.raises(KeyboardInterrupt):
            ex.run([Job(i, _square, (i,)) for i in range(3)], on_done=interrupt, progress=True, description="trials")
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("trials: 0/3 job stopped after"), err


def test_unreachable_ray_address_is_a_clear_input_error_before_ray_init(monkeypatch):
    """Nothing listening at --ray-address: an InputError naming the address in seconds. Before, the address
    went straight to ray.init, which retries for ~12 minutes printing Ray's own warnings (looked hung)."""
    import socket
    import time

    import ray

    def no_init(*a, **kw):
        raise AssertionError("ray.init was called with an address nobody answers at")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_init)
    # a port nobody listens on: held bound (not listening: connections are refused) for the whole check, so
    # that no other process (a Ray started by another test run) can take it meanwhile, as it could once released
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}"):
            t0 = time.monotonic()
            with pytest.raises(InputError, match=rf"no Ray cluster answers at '{address}'.*ray start --head"):
                make_executor(ExecutorOptions(ray_address=address))
            assert time.monotonic() - t0 < 10
    with pytest.raises(InputError, match="bad Ray address"):
        make_executor(ExecutorOptions(ray_address="head:port"))


def _loop_until_stopped(started: str, seconds: float) -> str:
    """A long task that polls for a stop between steps, as training does (`interrupt.check`)."""
    import time

    from splattwin import interrupt

    Path(started).write_text("running")
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        time.sleep(0.05)
        interrupt.check()
    return "finished"


def test_an_aborted_local_pool_stops_its_running_tasks(tmp_path):
    """The command stopped by SIGTERM (the CLI raises KeyboardInterrupt; `kill`, `timeout`, a pod's stop reach
    the command alone): the pool's workers are asked to stop their tasks. Before, closing the pool waited for
    every running task to finish (a whole build in `batch`)."""
    import time

    from splattwin import interrupt

    interrupt.install()   # as the CLI does before its pools fork
    try:
        started = tmp_path / "started"
        with pytest.raises(KeyboardInterrupt):
            with LocalExecutor(1) as ex:
                h = ex.submit(Job("long", _loop_until_stopped, (str(started), 60.0)))
                while not started.exists():
                    time.sleep(0.05)
                t0 = time.monotonic()
                raise KeyboardInterrupt   # what the driver loop raises on the command's SIGTERM
        assert time.monotonic() - t0 < 15
        # stopped by the worker's SIGTERM handler (ours: KeyboardInterrupt; after ray.init in this process,
        # Ray's: SystemExit), not "finished"
        assert isinstance(h.future.exception(), (KeyboardInterrupt, SystemExit))
    finally:
        interrupt.uninstall()


def test_a_worker_interrupted_itself_is_not_interrupted_twice(monkeypatch):
    """A terminal's Ctrl-C reaches the workers too: the pool's stop request then adds nothing (a second
    interrupt would stop a training step at once, losing its checkpoint)."""
    import signal

    from splattwin import executor, interrupt

    raised = []
    monkeypatch.setattr(signal, "getsignal", lambda signum: lambda *a: raised.append(a[0]))
    monkeypatch.setattr(interrupt, "stop_requested", lambda: True)
    executor._stop_as_interrupted(executor.STOP_SIGNAL, None)
    assert raised == []
    monkeypatch.setattr(interrupt, "stop_requested", lambda: False)
    executor._stop_as_interrupted(executor.STOP_SIGNAL, None)
    assert raised == [signal.SIGTERM]   # the SIGTERM handler, as on the worker's own SIGTERM
