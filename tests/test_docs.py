"""README.md and docs/*.md against the code: the flags they show exist on the commands they show them on,
links and section references resolve, the `splattwin.x.y` names and `docs/CONTRACTS.md` calls match the
code, the defaults the README states are the options' defaults, and the README's "Measured" headlines are
the figures of the docs/BENCHMARKS.md sections they link to. Text checks only (no training): well under 5 s."""

from __future__ import annotations

import argparse
import ast
import functools
import importlib
import inspect
import re
from pathlib import Path

import pytest

from splattwin.cli import build_parser

ROOT = Path(__file__).parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FLAG = re.compile(r"(?<![\w-])--(?:no-)?[a-z][a-z0-9_.-]*[a-z0-9]")
# flags of other programs the docs show in passing (`ray start --num-gpus N`)
FOREIGN_FLAGS = {"--num-gpus"}


def _parsers() -> dict[str, set[str]]:
    """Option strings of every (sub)command, keyed by its name below `splattwin` ("" = the top level)."""
    out: dict[str, set[str]] = {}

    def walk(p: argparse.ArgumentParser, name: str) -> None:
        out[name] = {s for a in p._actions for s in a.option_strings}
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub, sp in a.choices.items():
                    walk(sp, f"{name} {sub}".strip())
    walk(PARSER, "")
    return out


PARSER = build_parser()
PARSERS = _parsers()


@functools.cache
def _bench_flags() -> set[str]:
    """Flags of the bench/ scripts (the docs name them with the script: `bench/real.py --sections sfm`)."""
    flags = set()
    for f in (ROOT / "bench").glob("*.py"):
        flags |= set(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"", f.read_text()))
    return flags


def _code_spans(text: str) -> list[str]:
    """Shell lines of fenced blocks that run splattwin, and every inline `code` span (joined across lines)."""
    spans = []
    for m in re.finditer(r"```(\w*)\n(.*?)```", text, re.S):
        if m.group(1) in ("bash", "sh", ""):
            spans += [line.split(" #")[0] for line in m.group(2).splitlines() if "splattwin " in line]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    spans += [s.replace("\n", " ") for s in re.findall(r"`([^`]+)`", prose)]
    return spans


def flag_problems(text: str, parsers: dict[str, set[str]], bench: set[str]) -> list[str]:
    """Flags in `text` that the command they are shown with (or, shown alone, every command) lacks."""
    commands = sorted((c for c in parsers if c), key=len, reverse=True)
    everywhere = set().union(*parsers.values())
    problems = []
    for span in _code_spans(text):
        s = re.sub(r"^(\.venv/bin/)?splattwin\s+", "", span.strip())
        cmd = next((c for c in commands if re.match(re.escape(c) + r"(\s|$)", s)), None)
        if cmd is None and re.match(r"(python|ray |pip |kubectl|huggingface-cli)", s):
            continue
        pool = parsers[cmd] | parsers[""] if cmd else everywhere | bench | FOREIGN_FLAGS
        for flag in FLAG.findall(s):
            flag = flag.rstrip(".")
            # `--robot-capture.depth_noise.*`, `--cluster.*`: a prefix of real flags
            if flag not in pool and not any(f.startswith(flag + ".") for f in pool):
                problems.append(f"`{flag}` is no flag of `splattwin {cmd or '...'}` (in `{span.strip()[:80]}`)")
    return problems


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_documented_flags_exist(doc):
    assert flag_problems(doc.read_text(), PARSERS, _bench_flags()) == []


def test_flag_check_catches_a_misspelt_or_misplaced_flag():
    text = "`splattwin train DATA OUT --iters 5 --kappa 2` and `--splat.depth-lamda 0.1`"
    probs = flag_problems(text, PARSERS, set())
    assert len(probs) == 2 and "--kappa" in probs[0] and "--splat.depth-lamda" in probs[1]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _headings(path: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return [m.group(1).strip() for m in re.finditer(r"^#{1,6} (.+)$", text, re.M)]


def link_problems(doc: Path) -> list[str]:
    text = doc.read_text()
    problems = []
    for m in re.finditer(r"\]\(([^)\s]+)\)", text):
        target = m.group(1)
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = doc.parent / path if path else doc
        if not dest.exists():
            problems.append(f"link to a missing file: {target}")
        elif anchor and anchor not in {_slug(h) for h in _headings(dest)}:
            problems.append(f"link to a missing section: {target}")
    # `docs/BENCHMARKS.md, "Exposure"` / docs/BENCHMARKS.md, "CUDA backend on a GPU"
    for m in re.finditer(r"`?(docs/\w+\.md)`?,? \"([^\"]+)\"", text):
        if m.group(2) not in _headings(ROOT / m.group(1)):
            problems.append(f"no section \"{m.group(2)}\" in {m.group(1)}")
    # source files named in code spans: repo paths (`bench/real.py`) and package paths (`splat/mvs.py`)
    for m in re.finditer(r"`((?:[\w-]+/)+[\w-]+\.py)`", text):
        rel = m.group(1)
        if not any((base / rel).exists() for base in (ROOT, ROOT / "src", ROOT / "src" / "splattwin")):
            problems.append(f"no file {rel}")
    return problems


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_links_and_section_references_resolve(doc):
    assert link_problems(doc) == []


def _resolve(dotted: str):
    """The object a dotted `splattwin.a.b.C.d` name stands for, or None."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return None
            obj = getattr(obj, attr)
        return obj
    return None


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_named_modules_and_functions_exist(doc):
    names = sorted(set(re.findall(r"\bsplattwin(?:\.[A-Za-z_]\w*)+", doc.read_text())))
    assert [n for n in names if _resolve(n) is None] == []


def test_architecture_names_every_shared_module():
    """The layering diagram's "shared" line lists every top-level module (a new one must be placed)."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    # the line and its indented continuation, up to the end of the diagram
    line = re.search(r"^shared, importable by all[^:]*: (.*?)\n```", text, re.M | re.S).group(1).split()
    mods = {p.stem for p in (ROOT / "src" / "splattwin").glob("*.py")
            if not p.stem.startswith("_") and p.stem != "cli"}
    assert sorted(mods - set(line)) == [] and sorted(set(line) - mods) == []


# CONTRACTS.md calls: (call as written there, the callable it names). Each must bind to the signature.
CONTRACT_CALLS = [
    ("load_dataset(path, max_frames=None, validate=True, frames_dir=None, require_images=True, min_change=None)",
     "splattwin.capture.load_dataset"),
    ("bundle_frames(frames, out_dir)", "splattwin.capture.bundle.bundle_frames"),
    ("remove_unbundled(out_dir, earlier, placed, inputs)", "splattwin.capture.bundle.remove_unbundled"),
    ("pinhole_for(cam)", "splattwin.capture.undistort.pinhole_for"),
    ("undistort_image(img, cam, pinhole=None, nearest=False)", "splattwin.capture.undistort.undistort_image"),
    ("covering_pinhole(cam)", "splattwin.capture.undistort.covering_pinhole"),
    ("distort_image(img, pinhole, cam, nearest=False)", "splattwin.capture.undistort.distort_image"),
    ("apply_holdout(ds, HoldoutOptions)", "splattwin.poses.holdout.apply_holdout"),
    ("load_image(path)", "splattwin.capture.load_image"),
    ("load_depth(path)", "splattwin.capture.load_depth"),
    ("generate(out_dir, SceneOptions)", "splattwin.scene.generate"),
    ("rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=None, "
     "backgrounds=None, render_mode='RGB', near_plane=0.01, far_plane=1e10, eps2d=None, backend='auto', "
     "rasterize_mode='classic')", "splattwin.splat.rasterize.rasterization"),
    ("trained_filter(cfg)", "splattwin.splat.config.trained_filter"),
    ("filter_beside(ply)", "splattwin.splat.config.filter_beside"),
    ("Trainer(dataset, out, cfg, strategy=None)", "splattwin.splat.trainer.Trainer"),
    ("train(..., strategy=...)", "splattwin.splat.trainer.train"),
    ("masked_target(img, gt, quantile)", "splattwin.splat.robust.masked_target"),
    ("resolve_backend(name, device)", "splattwin.splat.rasterize.resolve_backend"),
    ("backend_device(name)", "splattwin.splat.rasterize.backend_device"),
    ("render_depth(gaussians, camera)", "splattwin.splat.rendering.render_depth"),
    ("fuse_to_dir(splats, dataset, masks, out, FusionOptions, metrics=False)", "splattwin.semantics.lift.fuse_to_dir"),
    ("build(out, options, from_stage=None, until=None, progress=True)", "splattwin.pipeline.build.build"),
    ("Stage(name, run, option_keys, deps, version, inputs, code)", "splattwin.pipeline.build.Stage",
     "Stage(name, run, option_keys, deps, version, inputs, code)"),
    ("stage_keys(out, options)", "splattwin.pipeline.build.stage_keys"),
    ("default_formats(frame)", "splattwin.twin.build.default_formats"),
    ("check_formats(frame, formats)", "splattwin.twin.build.check_formats"),
    ("unscaled_note(frame)", "splattwin.twin.manifest.unscaled_note"),
    ("run_once(..., keep_trajectories=True)", "splattwin.robot.trials.run_once"),
    ("DynamicScene.load(twin_dir)", "splattwin.playback.scene.DynamicScene.load"),
    ("RobotSplats.panda(T_world_base)", "splattwin.playback.robot.RobotSplats.panda"),
    ("PlaybackRenderer(scene, robot, relight=True, robot_shadows=True)",
     "splattwin.playback.compositor.PlaybackRenderer"),
    ("render(self, camera, object_poses, robot_pose)", "splattwin.playback.compositor.PlaybackRenderer.render"),
    ("camera_for(self, EyeInHand(), robot_pose)", "splattwin.playback.compositor.PlaybackRenderer.camera_for"),
    ("fill_mask(self, camera, object_poses)", "splattwin.playback.compositor.PlaybackRenderer.fill_mask"),
    ("render_rollout_video(renderer, rollout, camera, out_mp4, fps)", "splattwin.playback.movie.render_rollout_video"),
    ("write_episode(root, rollout, renderer, cameras, fps)", "splattwin.playback.episode.write_episode"),
    ("read_episode(root, index)", "splattwin.playback.episode.read_episode"),
    ("check_episode(episode, rollout, renderer, cameras)", "splattwin.playback.episode.check_episode"),
    ("Recorder(twin_dir, T_world_base, camera, width, fps)", "splattwin.playback.record.Recorder"),
    ("record(self, dest, runs)", "splattwin.playback.record.Recorder.record"),
    ("runs_of(robot_out, details, task)", "splattwin.playback.record.runs_of"),
    ("resolve_camera(spec, twin_dir)", "splattwin.playback.cameras.resolve_camera"),
    ("make_executor(ExecutorOptions, cpus_per_task=1.0, max_tasks=None)", "splattwin.executor.make_executor"),
    ("ExecutorOptions(executor='local', ray_address=None, max_retries=3, workers=None)",
     "splattwin.executor.ExecutorOptions"),
    ("run(self, [Job], on_done=None)", "splattwin.executor.Executor.run", "ex.run([Job("),
    ("Job(key, fn, args, resources, name)", "splattwin.executor.Job"),
    ("Resources(cpus=1, gpus=0)", "splattwin.executor.Resources"),
    ("Outcome(ok, value, error, attempts)", "splattwin.executor.Outcome"),
    ("run_trials(spec, n, sigma, out_dir=None, executor=None)", "splattwin.robot.trials.run_trials"),
    ("run_trial_job(spec, path)", "splattwin.robot.trials.run_trial_job"),
    ("SweepSpec(twin, grid={}, trial=None, trials=1)", "splattwin.cluster.sweep.SweepSpec"),
    ("run_sweep(SweepSpec, out, ex)", "splattwin.cluster.sweep.run_sweep", "run_sweep(SweepSpec("),
    ("run_batch(captures, out, options, ex, cpus=2, gpus=None)", "splattwin.cluster.batch.run_batch"),
    ("lost_outputs(twin_dir)", "splattwin.cluster.batch.lost_outputs"),
    ("object_name(text, where)", "splattwin.names.object_name"),
    ("view_name(text, where)", "splattwin.names.view_name"),
    ("check_unique(names, where)", "splattwin.names.check_unique"),
    ("confined(root, rel, where)", "splattwin.paths.confined"),
    ("child(root, name)", "splattwin.paths.child"),
    ("check_pixels(w, h)", "splattwin.limits.check_pixels"),
    ("check_count(n)", "splattwin.limits.check_count"),
    ("check_ply_header(path)", "splattwin.limits.check_ply_header"),
    ("load_mesh(path, what)", "splattwin.meshio.load_mesh"),
    ("output_lock(folder)", "splattwin.lock.output_lock"),
    ("InputError(problem, path)", "splattwin.errors.InputError"),
]


def _bind(call: str, fn) -> None:
    """Bind the call's arguments (values replaced by None) to `fn`'s signature; TypeError when they do not fit."""
    node = ast.parse(call, mode="eval").body
    sig = inspect.signature(fn)
    # `f(..., kw=...)`: the doc elides the leading arguments, so only what it names must fit
    elided = any(isinstance(a, ast.Constant) and a.value is Ellipsis for a in node.args)
    args = [None] * sum(not (isinstance(a, ast.Constant) and a.value is Ellipsis) for a in node.args)
    (sig.bind_partial if elided else sig.bind)(*args, **{k.arg: None for k in node.keywords})


def _fragment(entry: tuple) -> str:
    """How docs/CONTRACTS.md writes the call's start: `name(first argument` (`self` left out)."""
    if len(entry) > 2:
        return entry[2]
    node = ast.parse(entry[0], mode="eval").body
    args = [ast.unparse(a) for a in node.args if not (isinstance(a, ast.Name) and a.id == "self")]
    return entry[0].split("(")[0] + "(" + (args[0] if args else "")


@pytest.mark.parametrize("entry", CONTRACT_CALLS, ids=[c[1].rsplit(".", 1)[-1] for c in CONTRACT_CALLS])
def test_contracts_calls_bind(entry):
    """Each call as docs/CONTRACTS.md writes it binds to the current signature, and the doc still writes it."""
    fn = _resolve(entry[1])
    assert fn is not None, f"{entry[1]} does not exist"
    _bind(entry[0], fn)
    assert _fragment(entry) in re.sub(r"\s+", " ", (ROOT / "docs" / "CONTRACTS.md").read_text())


# Defaults the README states in words: (the README's phrase, the option's path in BuildOptions, its value in
# the unit the phrase uses, the factor from the option's unit to it).
README_DEFAULTS = [
    ("DBSCAN's largest cluster, eps 2 cm", "geometry.dbscan_eps", 2, 100),
    ("opacity below 0.1", "geometry.min_opacity", 0.1, 1),
    ("at least 90 %, `--geometry.rejoin-precision`", "geometry.rejoin_precision", 90, 100),
    ("at most 32, `--geometry.carve-views`", "geometry.carve_views", 32, 1),
    ("more than 2 mm in front of their rendered depth", "geometry.carve_tolerance", 2, 1000),
    ("within 5 cm (`--geometry.foot-gap`)", "geometry.foot_gap", 5, 100),
    ("more than 5 mm\n(`--geometry.float-gap`)", "geometry.float_gap", 5, 1000),
    ("grown by 1 cm (`--geometry.obstacle-pad`)", "geometry.obstacle_pad", 1, 100),
    ("`--geometry.density` 500 kg/m³", "geometry.density", 500, 1),
    ("(`--cpu-max-side`) are trained at 640 px", "splat.cpu_max_side", 640, 1),
    ("`--refine.iters N` (the demo: 800)", "refine.iters", 0, 1),
    ("default 1.0\ngrey level", "poses.min_change", 1.0, 1),
    ("(`off` the default", "splat.appearance", "off", None),
    ("(σ: per-axis std of the object x/y error, m)", "robot.sigma", 0.005, 1),
    ("`--max-retries`, default 3", "robot.cluster.max_retries", 3, 1),
    ("a capture with fewer than 10 training views trains with the sparse-view profile", "splat.sparse_views", 10, 1),
    ("3000 steps", "splat.iters", 3000, 1),
]


@pytest.mark.parametrize("phrase, path, value, factor", README_DEFAULTS, ids=[d[1] for d in README_DEFAULTS])
def test_readme_defaults_are_the_options_defaults(phrase, path, value, factor):
    from splattwin.pipeline.options import BuildOptions
    text = (ROOT / "README.md").read_text()
    assert phrase.replace("\n", " ") in re.sub(r"\s*\n\s*", " ", text)
    obj = BuildOptions()
    for part in path.split("."):
        obj = getattr(obj, part)
    assert (obj == value) if factor is None else obj * factor == pytest.approx(value)


def test_fusion_and_cli_defaults_match_the_readme():
    """README defaults that are no phrase naming one BuildOptions value (those are rows of README_DEFAULTS):
    the video frame count (a module constant), the fusion parameters, the viewer's address."""
    from splattwin.frame_options import VIDEO_MAX_FRAMES
    from splattwin.pipeline.options import BuildOptions
    text = re.sub(r"\s*\n\s*", " ", (ROOT / "README.md").read_text())
    assert "up to `--max-frames` (30) frames" in text and VIDEO_MAX_FRAMES == 30
    fusion = BuildOptions().semantics.fusion
    assert (fusion.kappa, fusion.eps, fusion.min_samples) == (1.5, 0.02, 10)
    assert "# http://127.0.0.1:8080" in text
    view = PARSERS["view"]
    assert {"--host", "--port"} <= view


def _benchmark_sections() -> dict[str, str]:
    """docs/BENCHMARKS.md's `## ` sections (their subsections included) by anchor."""
    out, cur = {}, None
    for line in (ROOT / "docs" / "BENCHMARKS.md").read_text().splitlines():
        if line.startswith("## "):
            cur = _slug(line[3:])
            out[cur] = ""
        elif cur:
            out[cur] += line + "\n"
    return out


def measured_problems(readme: str, sections: dict[str, str]) -> list[str]:
    """Numbers of a README "Measured" row that the BENCHMARKS section it links to does not contain."""
    table = readme.split("## Measured")[1].split("\n## ")[0]
    problems = []
    num = r"(?<![\w.])\d+(?:\.\d+)?(?!\w)"
    rows = 0
    for row in table.splitlines():
        m = re.search(r"\(\[details\]\(docs/BENCHMARKS\.md#([\w-]+)\)\)", row)
        if not m:
            continue
        rows += 1
        section = sections.get(m.group(1), "")
        for n in re.findall(num, row[:m.start()].split("|")[2]):
            if not re.search(r"(?<![\w.])" + re.escape(n) + r"(?![\d])", section):
                problems.append(f"{m.group(1)}: {n}")
    return problems if rows else ["no Measured rows"]


def test_measured_headlines_are_the_benchmarks_figures():
    assert measured_problems((ROOT / "README.md").read_text(), _benchmark_sections()) == []


def test_measured_check_catches_a_stale_headline():
    readme = ("## Measured\n| stage | figure |\n|---|---|\n| Rasterizer | 640×480 forward + backward 150 ms "
              "([details](docs/BENCHMARKS.md#rasterizer)) |\n")
    assert measured_problems(readme, _benchmark_sections()) == ["rasterizer: 150"]


CONTRACT_DATACLASSES = {"Frame": "splattwin.capture.Frame", "Dataset": "splattwin.capture.Dataset",
                        "Gaussians": "splattwin.splat.gaussians.Gaussians",
                        "Rollout": "splattwin.robot.rollout.Rollout"}


def test_contracts_dataclasses_list_every_field():
    """The `@dataclass class X:` blocks of docs/CONTRACTS.md list the class's fields, in order."""
    import dataclasses
    text = (ROOT / "docs" / "CONTRACTS.md").read_text()
    found = {}
    for m in re.finditer(r"@dataclass\nclass (\w+):[^\n]*\n((?:    [^\n]*\n)+)", text):
        found[m.group(1)] = re.findall(r"^    (\w+): ", m.group(2), re.M)
    assert sorted(found) == sorted(CONTRACT_DATACLASSES)
    for name, fields in found.items():
        cls = _resolve(CONTRACT_DATACLASSES[name])
        assert fields == [f.name for f in dataclasses.fields(cls)], name


@functools.cache
def _choices() -> dict[str, set[str]]:
    """The allowed values of every flag that has choices, over all commands."""
    out: dict[str, set[str]] = {}

    def walk(p: argparse.ArgumentParser) -> None:
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sp in a.choices.values():
                    walk(sp)
            elif a.choices:
                for s in a.option_strings:
                    out.setdefault(s, set()).update(map(str, a.choices))
    walk(PARSER)
    return out


def choice_problems(text: str, choices: dict[str, set[str]]) -> list[str]:
    """`--flag VALUE` / `--flag=A|B` spans whose values the flag does not accept."""
    problems = []
    for span in _code_spans(text):
        for m in re.finditer(r"(--[\w.-]+)[ =]([\w.+\-|\\]+)", span):
            if m.group(1) in choices:
                # a metavar (`--from STAGE`) or the next flag (`[--device --init]`) is no value
                values = [v for v in re.split(r"\\?\|", m.group(2)) if v and not v.isupper() and not v.startswith("--")]
                bad = [v for v in values if v not in choices[m.group(1)]]
                if bad:
                    problems.append(f"`{m.group(1)}` takes none of {bad} (in `{span.strip()[:80]}`)")
    return problems


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_documented_flag_values_are_accepted(doc):
    assert choice_problems(doc.read_text(), _choices()) == []


def test_value_check_catches_a_wrong_choice():
    assert len(choice_problems("`--splat.rasterize-mode antialias` and `--up=-z`", _choices())) == 1


def test_readme_twin_folder_lists_what_the_pipeline_writes():
    """Every TWIN/ entry of the pipeline's layout (pipeline/build.py's docstring, kept by its writers) and of
    CONTRACTS's twin layout is in the README's "The twin folder" listing."""
    import splattwin.pipeline.build as pipeline_build
    readme = (ROOT / "README.md").read_text()
    listing = re.search(r"## The twin folder\n+```\n(.*?)```", readme, re.S).group(1)
    listed = set(re.findall(r"^TWIN/([\w.]+)", listing, re.M))
    contracts = (ROOT / "docs" / "CONTRACTS.md").read_text()
    written = set(re.findall(r"TWIN/([\w.]+)", pipeline_build.__doc__ or "")) | set(
        re.findall(r"^TWIN/([\w.]+)", contracts.split("## Twin folder")[1].split("\n## ")[0], re.M))
    assert written and sorted(written - listed) == []
