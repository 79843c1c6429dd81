import json

import pytest

from splattwin.errors import InputError
from splattwin.pipeline.runner import Context, Stage, run_stages


def _stages(calls, fail_at=None):
    def make(name):
        def run(ctx):
            calls.append(name)
            if name == fail_at:
                raise KeyboardInterrupt  # a killed run
            (ctx.out / f"{name}.txt").write_text(str(ctx.options.get(name, 0)))
            return {"file": f"@{name}.txt"}
        return run
    return [Stage("a", make("a"), option_keys=("a",)),
            Stage("b", make("b"), option_keys=("b",), deps=("a",)),
            Stage("c", make("c"), option_keys=("c",), deps=("b",))]


def test_skip_finished_and_rerun_on_option_change(tmp_path):
    calls = []
    run_stages(_stages(calls), Context(tmp_path, {"a": 1, "b": 1, "c": 1}))
    assert calls == ["a", "b", "c"]
    calls.clear()
    run_stages(_stages(calls), Context(tmp_path, {"a": 1, "b": 1, "c": 1}))
    assert calls == []
    run_stages(_stages(calls), Context(tmp_path, {"a": 1, "b": 2, "c": 1}))
    assert calls == ["b", "c"]  # b's option changed; c depends on b


def test_from_stage_and_missing_output(tmp_path):
    calls = []
    opts = {"a": 1, "b": 1, "c": 1}
    run_stages(_stages(calls), Context(tmp_path, opts))
    calls.clear()
    run_stages(_stages(calls), Context(tmp_path, opts), from_stage="b")
    assert calls == ["b", "c"]
    calls.clear()
    (tmp_path / "c.txt").unlink()
    run_stages(_stages(calls), Context(tmp_path, opts))
    assert calls == ["c"]
    with pytest.raises(InputError, match="unknown stage"):
        run_stages(_stages(calls), Context(tmp_path, opts), from_stage="zzz")


def test_killed_run_resumes_without_redoing_finished_stages(tmp_path):
    calls = []
    opts = {"a": 1, "b": 1, "c": 1}
    with pytest.raises(KeyboardInterrupt):
        run_stages(_stages(calls, fail_at="b"), Context(tmp_path, opts))
    state = json.loads((tmp_path / "pipeline.json").read_text())
    assert list(state) == ["a"]
    calls.clear()
    ctx = run_stages(_stages(calls), Context(tmp_path, opts))
    assert calls == ["b", "c"]
    assert set(ctx.timings) == {"a", "b", "c"}


def test_a_rerun_stopped_midway_leaves_no_record_of_the_old_later_outputs(tmp_path):
    """New options for b, Ctrl-C during b: pipeline.json must not keep vouching for the old b and c
    (their files are still there, from the earlier options)."""
    calls = []
    run_stages(_stages(calls), Context(tmp_path, {"a": 1, "b": 1, "c": 1}))
    with pytest.raises(KeyboardInterrupt):
        run_stages(_stages(calls, fail_at="b"), Context(tmp_path, {"a": 1, "b": 2, "c": 1}))
    assert list(json.loads((tmp_path / "pipeline.json").read_text())) == ["a"]
    assert (tmp_path / "c.txt").is_file()   # files are left (a stage may resume from its own checkpoints)
    calls.clear()
    run_stages(_stages(calls), Context(tmp_path, {"a": 1, "b": 2, "c": 1}))
    assert calls == ["b", "c"]
