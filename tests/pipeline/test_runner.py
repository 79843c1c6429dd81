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


def test_from_names_the_stages_it_redoes_as_fresh(tmp_path):
    """--from b: b and c are redone on request (`ctx.fresh`: they must not resume partial work of their own);
    a plain re-run, or a killed run resumed, names none."""
    calls = []
    opts = {"a": 1, "b": 1, "c": 1}
    with pytest.raises(KeyboardInterrupt):
        run_stages(_stages(calls, fail_at="b"), Context(tmp_path, opts))
    assert run_stages(_stages(calls), Context(tmp_path, opts)).fresh == set()
    assert run_stages(_stages(calls), Context(tmp_path, opts), from_stage="b").fresh == {"b", "c"}
    assert run_stages(_stages(calls), Context(tmp_path, opts)).fresh == set()


def test_from_splats_retrains_instead_of_resuming_the_finished_run(scene_small, tmp_path):
    """The pipeline's splats stage on a finished twin: a re-run after a kill resumes the checkpoints, but
    `--from splats` retrains from step 0 (it used to resume the finished run's last checkpoint: no step
    trained, the stale figures kept)."""
    import shutil

    from splattwin.pipeline.build import _splats
    from splattwin.pipeline.options import BuildOptions
    from splattwin.splat.config import TrainConfig

    shutil.copytree(scene_small, tmp_path / "poses")
    cfg = BuildOptions(splat=TrainConfig(iters=20, checkpoint_every=10, sh_degree=1, max_gaussians=2000,
                                         backend="cpu", sparse_views=0))
    stages = [Stage("splats", _splats)]

    def trained(**kw) -> dict:
        run_stages(stages, Context(tmp_path, {}, config=cfg, progress=False), **kw)
        return json.loads((tmp_path / "splat" / "train.json").read_text())

    assert trained()["resumed_at_step"] is None
    (tmp_path / "pipeline.json").unlink()   # as after a kill between training and the stage's record
    assert trained()["resumed_at_step"] == 20   # the stage resumes its own checkpoints: nothing retrained
    rec = trained(from_stage="splats")
    assert rec["resumed_at_step"] is None and rec["steps"] == 20
    assert sorted(p.name for p in (tmp_path / "splat" / "checkpoints").iterdir()) == \
        ["ckpt_000010.safetensors", "ckpt_000020.safetensors"]


def test_a_stage_whose_outputs_were_rewritten_by_hand_runs_again(tmp_path):
    """`splattwin plan` run by hand with other options rewrites robot/results.json: the next build must not
    vouch for it as its own robot stage's output (it skipped the stage and kept the hand run's results)."""
    import os

    calls = []
    opts = {"a": 1, "b": 1, "c": 1}
    run_stages(_stages(calls), Context(tmp_path, opts))
    calls.clear()
    f = tmp_path / "b.txt"
    st = f.stat()
    f.write_text("9")                                   # another command's output, same size
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    run_stages(_stages(calls), Context(tmp_path, opts))
    assert calls == ["b", "c"] and f.read_text() == "1"
    calls.clear()
    run_stages(_stages(calls), Context(tmp_path, opts))
    assert calls == []


def test_an_oversized_pipeline_json_is_not_parsed(tmp_path, monkeypatch, caplog):
    """pipeline.json is a record (KBs): read under limits.MAX_RECORD_BYTES, not the 1 GiB of a COCO file; a
    larger one counts as corrupt (every stage runs again) instead of costing ~10x its size in memory."""
    import splattwin.limits

    calls = []
    run_stages(_stages(calls), Context(tmp_path, {"a": 1}))
    calls.clear()
    monkeypatch.setattr(splattwin.limits, "MAX_RECORD_BYTES", 16)
    run_stages(_stages(calls), Context(tmp_path, {"a": 1}))
    assert calls == ["a", "b", "c"] and "pipeline.json is corrupt" in caplog.text


@pytest.mark.parametrize("stage", ["semantics", "robot"])
def test_from_a_stage_reuses_none_of_its_saved_work(tmp_path, monkeypatch, stage):
    """`--from semantics` segmented nothing again (the saved prompt masks were resumed) and `--from robot`
    reused every stored trial: the stages resume their own partial work only when not redone on request."""
    from splattwin.pipeline import build as b
    from splattwin.pipeline.options import BuildOptions
    from splattwin.robot import stage as robot_stage
    from splattwin.robot.options import RobotOptions
    from splattwin.semantics import stage as sem_stage

    seen = []

    class Stop(Exception):
        pass

    def fake_sem(inputs, options, *, progress=True, fresh=False):
        seen.append(fresh)
        raise Stop

    def fake_robot(inputs, options, *, progress=True, record_errors=False):
        seen.append(not options.resume)
        raise Stop

    monkeypatch.setattr(sem_stage, "run", fake_sem)
    monkeypatch.setattr(robot_stage, "run", fake_robot)
    monkeypatch.setattr(b, "_semantics_inputs", lambda ctx: None)
    cfg = BuildOptions(robot=RobotOptions(task="default"))
    fn = b._semantics if stage == "semantics" else b._robot
    for fresh in (set(), {stage}):
        ctx = Context(tmp_path, {}, config=cfg, progress=False)
        ctx.fresh = set(fresh)
        with pytest.raises(Stop):
            fn(ctx)
    assert seen == [False, True]


def test_reexporting_an_unchanged_twin_does_not_redo_the_twin_stage(tmp_path):
    """`splattwin export TWIN` rewrites twin.json's timings (and lists the formats it adds): the next
    unchanged build redid the whole twin stage (geometry, convex decomposition, exports) because the
    runner hashed twin.json whole. Its run record is not the twin; an edit of the twin itself still counts."""
    calls = []

    def twin(ctx):
        calls.append("twin")
        doc = {"objects": [{"name": "box"}], "timings": {"export.mjcf": 0.29}, "exports": {"mjcf": "export/scene.xml"},
               "export_files": [], "versions": {"splattwin": "1"}}
        (ctx.out / "twin.json").write_text(json.dumps(doc))
        return {"manifest": "@twin.json"}

    stages = [Stage("twin", twin)]
    run_stages(stages, Context(tmp_path, {}))
    doc = json.loads((tmp_path / "twin.json").read_text())
    doc["timings"]["export.mjcf"] = 0.46                   # as `splattwin export --formats mjcf,gltf` writes it
    doc["exports"]["gltf"] = "export/scene.glb"
    doc["export_files"].append({"path": "export/scene.glb", "export": "gltf"})
    (tmp_path / "twin.json").write_text(json.dumps(doc, indent=2))
    ctx = run_stages(stages, Context(tmp_path, {}))
    assert calls == ["twin"] and ctx.skipped == ["twin"]
    doc["objects"][0]["name"] = "crate"                     # the twin itself, edited by hand
    (tmp_path / "twin.json").write_text(json.dumps(doc))
    run_stages(stages, Context(tmp_path, {}))
    assert calls == ["twin", "twin"]


def test_a_twin_json_digest_recorded_whole_still_matches_the_unchanged_file(tmp_path):
    """pipeline.json written before twin.json's run record was left out holds the whole file's digest:
    an unchanged twin must not be rebuilt (or reported unvouched) for that alone."""
    from splattwin.hashing import DigestCache, changed_outputs

    (tmp_path / "twin.json").write_text(json.dumps({"objects": [], "timings": {"geometry": 1.0}}))
    cache = DigestCache()
    rec = {"outputs": {"manifest": "@twin.json"}, "digests": {"@twin.json": cache.digest(tmp_path / "twin.json")}}
    assert changed_outputs(tmp_path, rec, cache) == []
    (tmp_path / "twin.json").write_text(json.dumps({"objects": [], "timings": {"geometry": 2.0}}))
    assert changed_outputs(tmp_path, rec, DigestCache()) == ["twin.json"]   # whole digest: any change shows
