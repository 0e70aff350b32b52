"""Every path argument and option of every command, typed as a user would: with spaces and
non-ASCII characters, through ``~``, ``..``, a symbolic link on the way, or relative to the
working folder; existing, missing, behind a dangling link, of the wrong kind, not a scene or not
writable. Each command either works (exit 0) or refuses with exit status 2 and one line that
names the path and the real cause (`svolsdf.io.paths`).

The work behind the checks is replaced by stand-ins (the pipeline's stages, structure from
motion, the MVS cascade, rendering, the synthetic renderer): the commands' own path handling,
argument parsing and the library's checks before any work run for real.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from svolsdf.cli import main
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

# --------------------------------------------------------------------------- the paths
#: characters of generated names: letters, digits, spaces, punctuation a desktop allows, and
#: non-ASCII letters (no "/", and no "~" or "-" at the start, which the shell and the option
#: parser read otherwise)
_CHARS = "abcXYZ019 _.,'()+=éüßñ日本語Ωж"
NAMES = st.text(_CHARS, min_size=1, max_size=10).filter(
    lambda s: s not in (".", "..") and not s.startswith("-"))

#: how the path is written: its real place is ROOT/p/DIR/NAME in every case
SPELLINGS = ("absolute", "relative", "tilde", "dotdot", "via_link")

#: what is at the path
STATES = ("valid", "link_valid", "missing", "missing_parent", "dangling", "dangling_far",
          "wrong_type", "not_scene", "read_only")


def _typed(spelling: str, root: Path, d: str, n: str) -> str:
    rel = f"p/{d}/{n}"
    return {"absolute": f"{root}/{rel}", "relative": rel, "tilde": f"~/{rel}",
            "dotdot": f"x/../{rel}", "via_link": f"plink/{d}/{n}"}[spelling]


# --------------------------------------------------------------------------- the commands
@dataclass(frozen=True)
class Case:
    """One path argument of one command.

    Attributes:
        name: "command argument", the test's id.
        kind: what the path must be: scene, run (a finished run folder), in_dir, in_file,
            in_path (a file or a folder), weights (a file whose content the command reads),
            out_dir, out_file.
        argv: (the path as typed, the fixtures) -> the command line.
        states: the states this argument is tried in (default: those of its kind).
        suffix: appended to the generated file name (".npy").
        not_scene: the words of the refusal of a folder that is not the scene wanted.
        works: a valid path makes the command work; False: the command may still refuse it
            for what is in it (junk weights, a DTU folder without the scan's files), in one
            line that names it.
    """

    name: str
    kind: str
    argv: Callable[[str, dict], list[str]]
    states: tuple[str, ...] = ()
    suffix: str = ""
    not_scene: str = "no known scene layout found (looked for "
    works: bool = True


_IN = ("valid", "link_valid", "missing", "missing_parent", "dangling", "dangling_far",
       "wrong_type")
_OUT = ("valid", "link_valid", "missing", "missing_parent", "dangling", "dangling_far",
        "wrong_type", "read_only")
KIND_STATES = {
    "scene": _IN + ("not_scene",), "run": _IN, "in_dir": _IN, "in_file": _IN,
    "in_path": _IN[:-1], "weights": _IN, "out_dir": _OUT,
    "out_file": ("valid", "missing_parent", "dangling_far", "wrong_type", "read_only"),
}


def _o(f):  # a fresh output folder beside the subject
    return str(f["fresh"] / "out")


CASES = [
    Case("info SCENE", "scene", lambda p, f: ["info", p]),
    Case("info --sheet", "out_file", lambda p, f: ["info", str(f["scene"]), "--sheet", p],
         suffix=".png"),
    Case("config --config", "in_file", lambda p, f: ["config", "--config", p]),
    Case("reconstruct SCENE", "scene", lambda p, f: ["reconstruct", p, "-o", _o(f),
                                                    "--no-progress"]),
    Case("reconstruct -o", "out_dir", lambda p, f: ["reconstruct", str(f["scene"]), "-o", p,
                                                   "--no-progress"]),
    Case("reconstruct --config", "in_file",
         lambda p, f: ["reconstruct", "--config", p, "-o", _o(f), "--no-progress"]),
    Case("reconstruct --weights", "weights",
         lambda p, f: ["reconstruct", str(f["scene"]), "-o", _o(f), "--backbone", "casmvsnet",
                       "--weights", p], suffix=".pt", works=False),
    Case("reconstruct --fusion-network", "weights",
         lambda p, f: ["reconstruct", str(f["scene"]), "-o", _o(f), "--fusion-network", p],
         suffix=".pt", works=False),
    Case("demo -o", "out_dir", lambda p, f: ["demo", "-o", p, "--no-progress"]),
    Case("calibrate INPUTS", "in_path", lambda p, f: ["calibrate", p, "-o", _o(f)]),
    Case("calibrate -o", "out_dir", lambda p, f: ["calibrate", str(f["scene"] / "image"), "-o",
                                                 p]),
    Case("mvs SCENE", "scene", lambda p, f: ["mvs", p, "-o", _o(f)]),
    Case("mvs -o", "out_dir", lambda p, f: ["mvs", str(f["scene"]), "-o", p]),
    Case("mvs --weights", "weights", lambda p, f: ["mvs", str(f["scene"]), "-o", _o(f),
                                                  "--backbone", "casmvsnet", "--weights", p],
         suffix=".pt"),
    Case("synth OUT", "out_dir", lambda p, f: ["synth", p, "--size", "32x24"]),
    Case("synth --cameras-from", "scene",
         lambda p, f: ["synth", _o(f), "--size", "32x24", "--cameras-from", p],
         not_scene="no cameras.npz or cameras_sphere.npz"),
    Case("evaluate OUT", "run", lambda p, f: ["evaluate", p, "--no-report"],
         states=_IN + ("read_only",)),
    Case("evaluate --gt-points", "in_file",
         lambda p, f: ["evaluate", str(f["run_copy"]), "--no-report", "--gt-points", p],
         suffix=".npy"),
    Case("evaluate --dtu-gt", "in_dir",
         lambda p, f: ["evaluate", str(f["run_copy"]), "--no-report", "--dtu-gt", p,
                       "--scan", "1"], works=False),
    Case("evaluate --scene", "scene",
         lambda p, f: ["evaluate", str(f["run_copy"]), "--no-report", "--scene", p]),
    Case("evaluate --lpips-weights", "in_path",
         lambda p, f: ["evaluate", str(f["run_copy"]), "--no-report", "--lpips-weights", p],
         works=False),
    Case("report OUT", "run", lambda p, f: ["report", p], states=_IN + ("read_only",)),
    Case("report --scene", "scene", lambda p, f: ["report", str(f["run_copy"]), "--scene", p]),
    Case("render OUT", "run", lambda p, f: ["render", p, "--views", "0"]),
    Case("benchmark --scenes", "scene",
         lambda p, f: ["benchmark", "--scenes", p, str(f["scene"]), "--modes", "mvs-only",
                       "-o", _o(f), "--no-render"]),
    Case("benchmark -o", "out_dir",
         lambda p, f: ["benchmark", "--scenes", str(f["scene"]), "--modes", "mvs-only", "-o", p,
                       "--no-render"]),
    Case("benchmark --dtu-gt", "in_dir",
         lambda p, f: ["benchmark", "--scenes", str(f["scene"]), "--modes", "mvs-only", "-o",
                       _o(f), "--no-render", "--dtu-gt", p]),
]


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A tiny scene and a run folder of it (points, views.json, config.yaml)."""
    from svolsdf.io.ply import read_ply, write_points_ply

    base = tmp_path_factory.mktemp("paths")
    scene = base / "scene"
    make_synthetic_scene(scene, SynthConfig(views=3, width=64, height=48, seed=2,
                                            supersample=1, gt_points=5000))
    run = base / "run"
    run.mkdir()
    write_points_ply(run / "points.ply", read_ply(scene / "gt_points.ply")["points"][::8])
    (run / "views.json").write_text(json.dumps({"inputs": [0, 1, 2], "test": [],
                                                "size": [64, 48], "scene": str(scene)}))
    (run / "config.yaml").write_text(f"scene:\n  path: {scene}\n")
    return {"base": base, "scene": scene, "run": run}


def _stand_ins(mp: pytest.MonkeyPatch, made: dict, empty_scores: bool) -> None:
    """Replace the work behind the commands (module docstring)."""
    import svolsdf.calibrate as calibrate
    import svolsdf.commands.mvs as mvs
    import svolsdf.commands.render as render
    import svolsdf.evaluate.scoring as scoring
    import svolsdf.scene.synthetic as synthetic
    from svolsdf.io.paths import user_path
    from svolsdf.pipeline import Pipeline

    # the pipeline's checks, folder, lock and log run; its stages do not
    mp.setattr(Pipeline, "_run", lambda self, t: {"points": None, "mesh": None,
                                                  "timing": {"total": {"seconds": 0.0}}})

    def calibrated(inputs, out, cfg):
        return {"num_inputs": 3, "registered": ["a", "b", "c"], "unregistered": [],
                "video": False, "size": [64, 48], "shared_camera": True,
                "matcher": "exhaustive", "mean_reprojection_error_px": 0.5,
                "seconds": {"total": 0.0}}

    mp.setattr(calibrate, "calibrate", calibrated)
    mp.setattr(mvs, "run_mvs", lambda cfg: {"backbone": cfg.backbone, "views": [0, 1, 2],
                                            "size": [64, 48], "seconds": {"total": 0.0}})

    def rendered(out, **kw):
        from svolsdf.pipeline.loaded_run import Run

        Run.open(out, field=False)  # the run folder's own checks
        return {"size": [64, 48], "files": [], "seconds_per_view": 0.0, "ibr_files": [],
                "video": None, "video_ibr": None}

    mp.setattr(render, "render_outputs", rendered)

    def synthesized(out, cfg):
        from svolsdf.io.replace import check_replace, replace_outputs

        spec, inputs = synthetic.SCENE_OUTPUT, [cfg.cameras_from]
        check_replace(user_path(out), spec, inputs)  # the folder's checks
        if cfg.cameras_from:
            synthetic._borrowed_cameras(cfg)  # the borrowed scene's
        with replace_outputs(user_path(out), spec, inputs) as stage:
            for name in spec.names:
                src = made["scene"] / name
                (shutil.copytree if src.is_dir() else shutil.copyfile)(src, stage / name)
        return user_path(out)

    mp.setattr(synthetic, "make_synthetic_scene", synthesized)
    if empty_scores:  # demo and benchmark score a run that the stand-in pipeline left empty
        mp.setattr(scoring, "evaluate_run", lambda cfg: {})


def _read_only(mp: pytest.MonkeyPatch, folder: Path) -> None:
    """Writing a file anywhere in ``folder`` fails as on a read-only mount (the tests run as
    root, whom permission bits do not stop)."""
    real = tempfile.mkstemp
    top = os.path.realpath(folder)

    def mkstemp(*a, dir=None, **k):
        if dir is not None and (os.path.realpath(dir) + "/").startswith(top + "/"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*a, dir=dir, **k)

    mp.setattr(tempfile, "mkstemp", mkstemp)


def _valid(kind: str, at: Path, made: dict) -> None:
    """Make what the argument wants at ``at``."""
    if kind == "scene":
        shutil.copytree(made["scene"], at)
    elif kind == "run":
        shutil.copytree(made["run"], at)
    elif kind in ("in_dir", "out_dir"):
        at.mkdir()
    elif kind == "in_path":
        shutil.copytree(made["scene"] / "image", at)
    elif kind == "in_file" and at.suffix == ".npy":
        np.save(at, np.random.default_rng(0).uniform(-1, 1, (50, 3)))
    elif kind == "in_file":
        at.write_text(f"scene: {{path: {made['scene']}}}\n")
    elif kind == "weights":
        at.write_bytes(b"not a checkpoint")
    elif kind != "out_file":
        raise AssertionError(kind)


def _build(case: Case, state: str, root: Path, d: str, n: str, made: dict
           ) -> tuple[Path | None, list[str]]:
    """Make the path's state at ROOT/p/D/N; returns (the folder a stand-in makes read-only or
    None, the words its refusal must hold: none when the command must work)."""
    p = root / "p"
    folder, at = p / d, p / d / n
    kind, ro, words = case.kind, None, []
    is_out = kind.startswith("out")
    if state != "missing_parent":
        folder.mkdir(parents=True)
    if state == "valid":
        _valid(kind, at, made)
    elif state == "link_valid":
        target = root / "targets" / f"t{case.suffix}"
        _valid(kind, target, made)
        at.symlink_to(target)
    elif state == "missing":
        words = [] if is_out else ["does not exist"]
    elif state == "missing_parent":
        words = [] if is_out else ["does not exist", d]
    elif state == "dangling":  # its target's folder exists: an output is made through it
        at.symlink_to(root / "targets" / f"{n}-t")
        words = [] if is_out else ["symbolic link to", f"{n}-t", "does not exist"]
    elif state == "dangling_far":
        at.symlink_to(root / "nowhere" / n)
        words = ["symbolic link to", str(root / "nowhere"), "does not exist"]
    elif state == "wrong_type":
        if kind in ("in_file", "weights", "out_file"):
            at.mkdir()
            words = ["is a folder, not a file"]
        else:
            at.write_text("a file")
            words = ["is a file, not a folder"]
    elif state == "not_scene":
        at.mkdir()
        (at / "notes.txt").write_text("no cameras here")
        words = [case.not_scene]
    elif state == "read_only":
        if kind == "run":
            _valid(kind, at, made)
            ro = at
        else:
            ro = folder
        words = ["cannot write", "Read-only file system"]
    else:
        raise AssertionError(state)
    return ro, words


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        main(argv)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
@settings(max_examples=10, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data(), d=NAMES, n=NAMES, spelling=st.sampled_from(SPELLINGS))
def test_every_path_argument_works_or_is_refused_with_its_cause(case, made, capsys, data, d,
                                                               n, spelling):
    from svolsdf.io.paths import user_path

    state = data.draw(st.sampled_from(case.states or KIND_STATES[case.kind]), label="state")
    n += case.suffix
    root = Path(tempfile.mkdtemp(prefix="case ", dir=made["base"]))
    try:
        for sub in ("p", "x", "targets", "fresh"):
            (root / sub).mkdir()
        (root / "plink").symlink_to(root / "p")
        ro, words = _build(case, state, root, d, n, made)
        fixtures = {**made, "fresh": root / "fresh", "run_copy": root / "fresh" / "run"}
        shutil.copytree(made["run"], fixtures["run_copy"])  # evaluate and report write in it
        typed = _typed(spelling, root, d, n)
        argv = case.argv(typed, fixtures)
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("HOME", str(root))
            mp.chdir(root)
            _stand_ins(mp, made, empty_scores=case.name.startswith(("demo", "benchmark")))
            if ro is not None:
                _read_only(mp, ro)
            code, out, err = _run(argv, capsys)
            # the path as typed, with ~ expanded, or where it leads
            names = (typed, str(user_path(typed)), os.path.realpath(user_path(typed)))
        where = f"{case.name}, {state}, {spelling}: {argv}: exit {code}\n{err}"
        if not words and (case.works or code == 0):
            assert code == 0, where  # it works
            return
        # refused: exit 2, one line naming the path and the cause
        assert code == 2, where
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), where
        assert any(s in lines[0] for s in names), where
        assert all(w in lines[0] for w in words), where
    finally:
        shutil.rmtree(root, ignore_errors=True)


# --------------------------------------------------------------------------- the reported cases
def test_benchmark_takes_a_quoted_scene_path_with_spaces_as_one_scene(made, tmp_path, capsys,
                                                                      monkeypatch):
    """``svolsdf benchmark --scenes "/data/my scans/scan 1" -o OUT`` once split the argument on
    its spaces and answered "/data/my: scene folder does not exist"."""
    scans = tmp_path / "my scans"
    scene = scans / "scan 1"
    shutil.copytree(made["scene"], scene)
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, made, empty_scores=True)
        code, out, err = _run(["benchmark", "--scenes", str(scene), "--modes", "mvs-only",
                               "-o", str(tmp_path / "b"), "--no-render"], capsys)
    assert code == 0, err
    assert "| scan 1 |" in out and (tmp_path / "b" / "scan 1" / "mvs-only").is_dir()
    # two scenes, each one argument, and the option repeated: the same
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, made, empty_scores=True)
        code, out, err = _run(["benchmark", "--scenes", str(scene), "--scenes",
                               str(made["scene"]), "--modes", "mvs-only", "-o",
                               str(tmp_path / "b2"), "--no-render"], capsys)
    assert code == 0 and "| scan 1 |" in out and "| scene |" in out, err
    # a missing one is named whole, with the first part of it that is missing
    code, out, err = _run(["benchmark", "--scenes", str(tmp_path / "my scan" / "scan 1"), "-o",
                           str(tmp_path / "b3")], capsys)
    assert code == 2 and err.strip() == (
        f"error: --scenes {tmp_path}/my scan/scan 1: scene folder does not exist: "
        f"{tmp_path}/my scan does not exist")


def test_reconstruct_into_a_link_to_a_folder_not_made_yet(made, tmp_path, capsys):
    """``svolsdf reconstruct SCENE -o LINK``, LINK a symbolic link to a folder that does not
    exist yet, once answered "cannot write the output folder (File exists)"."""
    link = tmp_path / "run link"
    link.symlink_to(tmp_path / "runs" / "run 1")
    (tmp_path / "runs").mkdir()
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, made, empty_scores=False)
        code, out, err = _run(["reconstruct", str(made["scene"]), "-o", str(link),
                               "--no-progress"], capsys)
    assert code == 0, err
    # made where the link points; the link stays a link
    assert link.is_symlink() and (tmp_path / "runs" / "run 1" / "log").is_file()
    # a link whose target's folder is missing too is refused, naming link, target and folder
    far = tmp_path / "far link"
    far.symlink_to(tmp_path / "disk" / "run 1")
    code, out, err = _run(["reconstruct", str(made["scene"]), "-o", str(far)], capsys)
    assert code == 2 and err.strip() == (
        f"error: -o {far}: output folder is a symbolic link to {tmp_path}/disk/run 1, which "
        f"does not exist, and it cannot be made there: {tmp_path}/disk does not exist; create "
        "that folder or point the link elsewhere")
    assert not (tmp_path / "disk").exists()
