"""Every command that replaces a scene-like folder (calibrate, synth, demo), run over its own
earlier output with a user's files in and around it, with a bad input and with a good one:
nothing the command did not write is ever gone (`svolsdf.io.replace`).

- a bad input ends in exit status 2 and one line, and nothing under the test's folder changed
  (not a byte, not a timestamp's worth of new files), and structure from motion never started;
- a good input with a user's file inside a folder the command replaces is refused the same way;
- a good input otherwise replaces the earlier output (files of it that the new output lacks are
  gone) and keeps every file of the user's: beside the output, at its top, and the input photos
  when they live inside it.

Structure from motion runs for real on 8 small views (about 2 s); the synthetic renderer's
result is rendered once per setting (with a coarse ground truth) and copied after that, and the
demo's reconstruction and scoring are stand-ins (its scene, folders and checks are real).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from svolsdf.cli import main
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

# 8 views of one camera, small: structure from motion registers all 8 in about 2 s
PHOTOS = SynthConfig(views=8, width=256, height=192, seed=0, intrinsics_jitter=0.0,
                     supersample=1, gt_points=5000, mesh_resolution=4.0)
CAL = ["--threads", "1", "--no-progress"]


@dataclass(frozen=True)
class Writer:
    """One command that writes a scene-like folder.

    Attributes:
        name: the command.
        earlier: (OUT, fixtures) -> the command line that made the earlier output.
        good: (OUT, fixtures, photos) -> a command line with good inputs that replaces it.
        bad: {name: (OUT, fixtures) -> a command line with a bad input}.
        inner: a folder the command replaces, where a user's file is refused.
        gone: a file of the earlier output that the good run's output lacks.
        check: (OUT) -> asserts that OUT holds the good run's output.
    """

    name: str
    earlier: Callable[[Path, dict], list[str]]
    good: Callable[[Path, dict, Path], list[str]]
    bad: dict[str, Callable[[Path, dict], list[str]]]
    inner: str
    gone: str | None
    check: Callable[[Path], None]


def _scene_json(folder: Path) -> dict:
    return json.loads((folder / "scene.json").read_text())


def _check_calibrate(out: Path) -> None:
    s = json.loads((out / "calibration.json").read_text())
    assert len(s["registered"]) >= 3 and (out / "sparse" / "0" / "images.txt").is_file()
    assert sorted(p.name for p in (out / "images").iterdir()) == s["registered"]


def _check_synth(out: Path) -> None:
    assert _scene_json(out)["views"] == 2


def _check_demo(out: Path) -> None:
    assert _scene_json(out / "scene")["config"]["seed"] == 1
    assert (out / "run" / "demo_metrics.json").is_file()


WRITERS = [
    Writer("calibrate",
           lambda o, f: ["calibrate", str(f["photos"]), "-o", str(o), *CAL],
           lambda o, f, photos: ["calibrate", str(photos), "-o", str(o), *CAL],
           {"no photos": lambda o, f: ["calibrate", str(f["empty"]), "-o", str(o), *CAL],
            "unreadable photos": lambda o, f: ["calibrate", str(f["junk"]), "-o", str(o), *CAL],
            "the earlier output's images": lambda o, f: ["calibrate", str(o / "images"), "-o",
                                                         str(o), *CAL],
            "a bad option": lambda o, f: ["calibrate", str(f["photos"]), "-o", str(o),
                                          "--max-size", "10", *CAL]},
           inner="images", gone=None, check=_check_calibrate),
    Writer("synth",
           lambda o, f: ["synth", str(o), "--size", "32x24", "--views", "3"],
           lambda o, f, photos: ["synth", str(o), "--size", "32x24", "--views", "2"],
           {"no cameras to borrow": lambda o, f: ["synth", str(o), "--size", "32x24",
                                                  "--cameras-from", str(f["empty"])],
            "too small": lambda o, f: ["synth", str(o), "--size", "8x8"],
            "an unknown object": lambda o, f: ["synth", str(o), "--object", "teapot"]},
           inner="image", gone="image/000002.png", check=_check_synth),
    Writer("demo",
           lambda o, f: ["demo", "-o", str(o), "--size", "32x24", "--no-progress"],
           lambda o, f, photos: ["demo", "-o", str(o), "--size", "32x24", "--seed", "1",
                                 "--no-progress"],
           {"negative steps": lambda o, f: ["demo", "-o", str(o), "--size", "32x24",
                                            "--steps", "-1"],
            "too small": lambda o, f: ["demo", "-o", str(o), "--size", "8x8"]},
           inner="scene/image", gone=None, check=_check_demo),
]


def _snapshot(root: Path) -> dict[str, str]:
    """Every entry under ``root``: files by content, folders, links by target."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for n in dirs + files:
            p = Path(dirpath) / n
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = "link " + os.readlink(p)
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _run(argv: list[str], capsys) -> tuple[int, str]:
    try:
        main(argv)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    """The photos, bad input folders, a render cache, and each command's earlier output."""
    base = tmp_path_factory.mktemp("outputs")
    scene = base / "photos_scene"
    make_synthetic_scene(scene, PHOTOS)
    empty, junk = base / "empty", base / "junk"
    empty.mkdir()
    junk.mkdir()
    for k in range(3):
        (junk / f"{k}.jpg").write_bytes(b"not a photo")
    f = {"base": base, "photos": scene / "image", "empty": empty, "junk": junk,
         "renders": {}, "sfm_runs": [], "earlier": {}}
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, f)
        for w in WRITERS:
            out = base / "earlier" / w.name
            code, err = _run(w.earlier(out, f), _NoCapture())
            assert code == 0, err
            f["earlier"][w.name] = out
    return f


class _NoCapture:
    def readouterr(self):
        return type("R", (), {"err": "", "out": ""})()


def _stand_ins(mp: pytest.MonkeyPatch, f: dict) -> None:
    """Count structure-from-motion runs; render each synthetic setting once; the demo's
    reconstruction and scoring as stand-ins."""
    import svolsdf.calibrate.sfm as sfm
    import svolsdf.evaluate.scoring as scoring
    import svolsdf.scene.synthetic as synthetic
    from svolsdf.pipeline import Pipeline

    real_sfm, real_render = sfm._run_sfm, getattr(synthetic, "_render_scene", None)

    def counted_sfm(*a, **k):
        f["sfm_runs"].append(1)
        return real_sfm(*a, **k)

    def cached_render(out, cfg, borrowed):
        key = json.dumps(asdict(cfg), sort_keys=True, default=str)
        if key not in f["renders"]:
            d = f["base"] / "renders" / str(len(f["renders"]))
            d.mkdir(parents=True)
            # a coarse ground truth (the views are the setting's), recorded as the setting's
            cheap = replace(cfg, gt_points=2000, mesh_resolution=max(cfg.mesh_resolution, 6.0))
            f["renders"][key] = d, real_render(d, cheap, borrowed)
            meta = json.loads((d / "scene.json").read_text())
            meta["config"] = json.loads(key)
            (d / "scene.json").write_text(json.dumps(meta))
        d, result = f["renders"][key]
        for p in d.iterdir():
            (shutil.copytree if p.is_dir() else shutil.copyfile)(p, out / p.name)
        return result

    mp.setattr(sfm, "_run_sfm", counted_sfm)
    mp.setattr(synthetic, "_render_scene", cached_render, raising=False)
    mp.setattr(Pipeline, "_run", lambda self, t: {"points": None, "mesh": None,
                                                  "timing": {"total": {"seconds": 0.0}}})
    mp.setattr(scoring, "evaluate_run", lambda cfg: {})


PLACES = ("beside", "top", "inner", "photos inside")


@pytest.mark.parametrize("w", WRITERS, ids=[w.name for w in WRITERS])
@settings(max_examples=8, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data(), places=st.sets(st.sampled_from(PLACES)))
def test_nothing_the_command_did_not_write_is_gone(w, fx, tmp_path_factory, capsys, data,
                                                   places):
    bad = data.draw(st.sampled_from([None, *w.bad]), label="bad input")
    root = tmp_path_factory.mktemp("case")
    out = root / "out"
    shutil.copytree(fx["earlier"][w.name], out)
    mine = {}  # the user's files: path -> content
    if "beside" in places:
        mine[root / "beside.txt"] = b"next to the output"
    if "top" in places:
        mine[out / "notes.txt"] = b"my notes"
    if "inner" in places:
        mine[out / w.inner / "mine.png"] = b"my own picture"
    photos = fx["photos"]
    if "photos inside" in places and w.name == "calibrate":
        photos = out / "photos"  # the layout calibrate PHOTOS -o SCENE suggests
        shutil.copytree(fx["photos"], photos)
        mine.update({p: p.read_bytes() for p in photos.iterdir()})
    for p, content in mine.items():
        p.write_bytes(content)
    before = _snapshot(root)
    earlier = _snapshot(out)
    fx["sfm_runs"].clear()
    argv = w.good(out, fx, photos) if bad is None else w.bad[bad](out, fx)
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, fx)
        code, err = _run(argv, capsys)
    where = f"{w.name}, {bad or 'good input'}, {sorted(places)}: {argv}: exit {code}\n{err}"
    if bad is not None or "inner" in places:
        # refused before any work: one line, and not a byte changed
        assert code == 2, where
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), where
        if bad is None:
            assert str(out / w.inner / "mine.png") in lines[0], where
        assert _snapshot(root) == before, where
        assert not fx["sfm_runs"], where  # no structure from motion started
        return
    assert code == 0, where
    for p, content in mine.items():
        assert p.read_bytes() == content, (where, p)
    w.check(out)
    if w.gone is not None:
        assert w.gone in earlier and not (out / w.gone).exists(), where
    left = [p.name for p in out.iterdir()
            if p.name.startswith((".svolsdf-staging.", ".svolsdf-replaced."))]
    assert not left, (where, left)


# --------------------------------------------------------------------------- the reported cases
def test_calibrate_with_a_bad_input_keeps_the_earlier_calibration(fx, tmp_path, capsys):
    """``calibrate PHOTOS -o PREV`` once deleted PREV/images, sparse and calibration.json and
    only then refused the photos; ``calibrate PREV/images -o PREV`` deleted the photos and then
    said that the input folder did not exist."""
    prev = tmp_path / "prev"
    shutil.copytree(fx["earlier"]["calibrate"], prev)
    before = _snapshot(prev)
    for argv in (["calibrate", str(fx["junk"]), "-o", str(prev)],
                 ["calibrate", str(prev / "images"), "-o", str(prev)]):
        code, err = _run(argv, capsys)
        assert code == 2 and _snapshot(prev) == before, err
    assert f"the input {prev / 'images'} is {prev / 'images'}, which svolsdf calibrate " \
           "replaces" in err


def test_synth_keeps_a_file_the_user_put_in_its_image_folder(fx, tmp_path, capsys):
    out = tmp_path / "s"
    shutil.copytree(fx["earlier"]["synth"], out)
    (out / "image" / "mine.png").write_bytes(b"mine")
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, fx)
        code, err = _run(["synth", str(out), "--size", "32x24", "--views", "3"], capsys)
    assert code == 2 and (out / "image" / "mine.png").read_bytes() == b"mine", err
    assert f"{out / 'image' / 'mine.png'} is not a file svolsdf synth wrote" in err


def test_demo_makes_its_scene_again_when_the_size_changes(fx, tmp_path, capsys):
    """A second ``svolsdf demo --size`` once reused the first size's scene and results."""
    from svolsdf.pipeline import Pipeline

    out = tmp_path / "demo"
    shutil.copytree(fx["earlier"]["demo"], out)
    seen = []
    with pytest.MonkeyPatch.context() as mp:
        _stand_ins(mp, fx)
        real = Pipeline._run
        mp.setattr(Pipeline, "_run", lambda self, t: (seen.append(
            _scene_json(Path(self.cfg.scene.path))["width"]), real(self, t))[1])
        code, err = _run(["demo", "-o", str(out), "--size", "40x30", "--no-progress"], capsys)
        assert code == 0, err
        made = (out / "scene" / "image").stat().st_ino  # a scene made again is a new folder
        code, err = _run(["demo", "-o", str(out), "--size", "40x30", "--no-progress"], capsys)
        assert code == 0, err
    # made again for the new size, then reused; the reconstruction ran on the new scene
    assert seen == [40, 40] and _scene_json(out / "scene")["height"] == 30
    assert (out / "scene" / "image").stat().st_ino == made


@pytest.mark.parametrize("where", ["the scene", "inside it", "holding it", "another scene"])
def test_benchmark_and_demo_write_into_no_scene_folder(fx, tmp_path, capsys, where):
    scene = tmp_path / "data" / "scan1"
    shutil.copytree(fx["earlier"]["synth"], scene)
    other = tmp_path / "other"
    shutil.copytree(fx["earlier"]["synth"], other)
    out = {"the scene": scene, "inside it": scene / "runs", "holding it": tmp_path / "data",
           "another scene": other}[where]
    before = _snapshot(tmp_path)
    code, err = _run(["benchmark", "--scenes", str(scene), "--modes", "mvs-only", "-o",
                      str(out), "--no-render"], capsys)
    assert code == 2 and f"-o {out}: " in err and "folder of its own" in err, err
    if where != "holding it":  # the demo reads no scene: it is refused in and inside any
        code, err = _run(["demo", "-o", str(out), "--size", "32x24"], capsys)
        assert code == 2 and f"-o {out}: " in err and "folder of its own" in err, err
    assert _snapshot(tmp_path) == before
