"""A run folder you can trust (issue 42): stage keys that follow the inputs' contents, the config
that made each output, one lock for every writer, and degenerate input refused before any stage."""

from __future__ import annotations

import errno
import json
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from tests.pipeline.tiny_pipeline import cli as _main
from tests.pipeline.tiny_pipeline import cli_exit as _run
from tests.pipeline.tiny_pipeline import copy_run as _copy
from tests.pipeline.tiny_pipeline import make_small_sphere_scene, small_field_run

from svolsdf.config import preset
from svolsdf.errors import InputError
from svolsdf.pipeline import STAGES, Run
from svolsdf.pipeline.keys import input_keys, input_manifest


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_small_sphere_scene(tmp_path_factory.mktemp("rf") / "scene")


@pytest.fixture(scope="module")
def mvs_run(scene, tmp_path_factory):
    """A finished mvs-only run of views 0 1 2 (seconds)."""
    out = tmp_path_factory.mktemp("rfrun") / "run"
    _main(["reconstruct", str(scene), "-o", str(out), "--mode", "mvs-only", "--views", "0", "1",
          "2", "--no-progress"])
    return out


@pytest.fixture(scope="module")
def field_run(scene, tmp_path_factory):
    """A finished run with a field (a 16^3 grid, 10 steps: seconds)."""
    return small_field_run(scene, tmp_path_factory.mktemp("rffield"))


def _keys_of(scene_dir: Path, cfg) -> dict[str, str]:
    cfg.scene.path, cfg.scene.views = str(scene_dir), [0, 1, 2]
    return input_keys(cfg, input_manifest(Run(cfg, scene_dir / "unused").load()))


def _mutate(path: Path) -> None:
    """Change a file's content the way a user replacing it would."""
    if path.suffix == ".png":
        a = np.array(Image.open(path))
        a[: a.shape[0] // 2] = 255 - a[: a.shape[0] // 2]
        Image.fromarray(a).save(path)
    elif path.suffix == ".npz":
        d = dict(np.load(path))
        for k in d:
            if k.startswith("world_mat"):
                d[k] = d[k] * 1.0
                d[k][0, 3] += 0.5  # move every camera a little (its image still fits it)
        np.savez(path, **d)
    elif path.suffix == ".npy":
        np.save(path, np.load(path) + 1)
    else:
        path.write_bytes(path.read_bytes() + b"\n")


# --------------------------------------------------------------------------- 1: inputs' contents
def test_mutating_any_input_file_changes_exactly_the_stages_that_read_it(scene, tmp_path):
    cfg = preset("fast")
    assert cfg.scene.use_masks and cfg.guide.mask_dilation is not None
    base = _keys_of(scene, cfg)
    # what reads what: every stage the pictures and cameras of the input views (stage 1 first);
    # the masks every stage but stage 1 and the unguided stages 2-3 (the cascade takes none)
    every, masks = set(STAGES), set(STAGES) - {"mvs1", "unguided"}
    files = sorted(p for p in scene.rglob("*") if p.is_file())
    assert len(files) > 10
    for f in files:
        rel = f.relative_to(scene)
        want: set[str] = set()
        if rel.parts[0] in ("image", "mask") and int(f.stem) in (0, 1, 2):
            want = every if rel.parts[0] == "image" else masks
        elif rel.name in ("cameras.npz", "cameras_sphere.npz"):
            want = every
        copy = tmp_path / f"s_{len(list(tmp_path.iterdir()))}"
        shutil.copytree(scene, copy)
        _mutate(copy / rel)
        new = _keys_of(copy, cfg)
        changed = {s for s in STAGES if new[s] != base[s]}
        assert changed == want, (rel, changed, want)
        shutil.rmtree(copy)


def test_a_replaced_image_recomputes_with_a_log_line_and_touch_does_not(mvs_run, scene,
                                                                        tmp_path, capsys):
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    out = _copy(mvs_run, tmp_path / "run")
    cfg = (out / "config.yaml").read_text().replace(str(scene), str(sc))
    (out / "config.yaml").write_text(cfg)
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    before = json.loads((out / "stages.json").read_text())
    img = sc / "image" / "000001.png"
    img.touch()  # a new modification time, the same content: nothing to recompute
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    assert "inputs changed" not in (out / "log").read_text()
    pts = (out / "points.ply").read_bytes()
    # the same path, another picture: the stages that read it run again, and the log says why
    a = np.array(Image.open(sc / "image" / "000003.png"))
    Image.fromarray(a).save(img)
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    log = (out / "log").read_text()
    assert f"image of view 1 ({img}, changed)" in log
    assert "stage mvs1: its inputs changed since it finished" in log
    after = json.loads((out / "stages.json").read_text())
    assert after["provenance"]["mvs1"]["inputs"] != before["provenance"]["mvs1"]["inputs"]
    assert (out / "points.ply").read_bytes() != pts


def test_a_run_folder_from_before_the_record_keeps_its_stages(mvs_run, tmp_path):
    out = _copy(mvs_run, tmp_path / "run")
    st = json.loads((out / "stages.json").read_text())
    old = {k: v for k, v in st.items() if k in STAGES}  # as run folders were written before
    (out / "stages.json").write_text(json.dumps(old))
    t = json.loads((out / "timing.json").read_text())["mvs1"]["seconds"]
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    log = (out / "log").read_text()
    assert "finished before their inputs were recorded are kept" in log
    assert json.loads((out / "timing.json").read_text())["mvs1"]["seconds"] == t  # not rerun
    st = json.loads((out / "stages.json").read_text())
    assert {k: st[k] for k in old} == old and st["provenance"]["fusion"]["inputs"]  # adopted


def _truncate(path: Path) -> None:
    """Cut a file to half its bytes, as a full disk or a killed copy leaves it."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _without_output_records(out: Path) -> None:
    """Drop the record of the finished stages' files from stages.json, as run folders were
    written before it: a file is then checked only by reading it."""
    st = json.loads((out / "stages.json").read_text())
    del st["outputs"]
    (out / "stages.json").write_text(json.dumps(st))


@pytest.mark.parametrize("stage, rel", [("mvs1", "mvs/stage1/1.npz"), ("mvs23", "depth/1.npy")])
def test_a_stage_whose_file_cannot_be_read_runs_again_and_says_so(mvs_run, tmp_path, stage,
                                                                   rel):
    """Issue 50: a truncated stage file is no bug: the stage (and the later ones) run again, and
    OUT/log and the stage's entry in timing.json (copied into metrics.json and the report) say
    that it ran again because that file could not be read."""
    out = _copy(mvs_run, tmp_path / "run")
    _without_output_records(out)  # else the record finds it first (test_output_records.py)
    _truncate(out / rel)
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    why = json.loads((out / "timing.json").read_text())[stage]["rerun"]
    assert why.startswith(f"{out / rel} could not be read ("), why
    log = (out / "log").read_text()
    assert f"{out / rel} could not be read (" in log and f"running the stage {stage} again" in log
    if rel.endswith(".npz"):
        from svolsdf.mvs.volume import ProbabilityVolume

        ProbabilityVolume.load(out / rel)
    else:
        np.load(out / rel)  # whole again


@pytest.mark.parametrize("bug", [TypeError, AttributeError, NameError])
def test_a_bug_in_a_loader_propagates_and_keeps_the_stages(mvs_run, field_run, tmp_path,
                                                           monkeypatch, bug):
    """Issue 50: only what a truncated, corrupt or older file raises reruns a stage; a loader's
    own bug (TypeError, AttributeError, NameError) reaches the caller, and no stage is forgotten."""
    from svolsdf.config import load_config
    from svolsdf.mvs.volume import ProbabilityVolume
    from svolsdf.pipeline import Pipeline
    from svolsdf.pipeline.stages import field as stages_module

    def broken(*args, **kwargs):
        raise bug("a loader's bug")

    for src, target, name in ((mvs_run, ProbabilityVolume, "load"),
                              (field_run, stages_module, "load_model")):
        out = _copy(src, tmp_path / f"run_{name}")
        state = (out / "stages.json").read_text()
        with monkeypatch.context() as m:
            m.setattr(target, name, broken)
            with pytest.raises(bug, match="a loader's bug"):
                Pipeline(load_config(out / "config.yaml"), out, progress=False).run()
        assert (out / "stages.json").read_text() == state
        assert "could not be read" not in (out / "log").read_text()


def test_a_truncated_field_is_discarded_and_fitted_again(field_run, tmp_path):
    """The field's model.pt (torch's zip) cut short: discarded, the field fitted again, and
    timing.json's field entry says why."""
    out = _copy(field_run, tmp_path / "run")
    _without_output_records(out)
    _truncate(out / "field" / "model.pt")
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    timing = json.loads((out / "timing.json").read_text())
    assert timing["field"]["rerun"].startswith(f"{out / 'field' / 'model.pt'} could not be read")
    assert "discarding it and running the stage field again" in (out / "log").read_text()
    torch.load(out / "field" / "model.pt", weights_only=False)


# --------------------------------------------------------------------------- 2: provenance
def test_outputs_of_an_earlier_config_are_refused_by_evaluate_and_report(mvs_run, tmp_path,
                                                                         capsys, monkeypatch):
    import svolsdf.pipeline as pl
    from svolsdf.config import load_config

    out = _copy(mvs_run, tmp_path / "run")
    _main(["evaluate", out, "--no-report"])
    m = json.loads((out / "metrics.json").read_text())
    assert m["settings"]["provenance"] == {"points.ply": "config.yaml"}
    cfg = load_config(out / "config.yaml")
    cfg.fusion.min_views = 2  # a rerun with a new option, killed before fusion
    from svolsdf.pipeline.stages.fusion import Fusion

    monkeypatch.setattr(Fusion, "run", lambda self, ctx, inputs: (_ for _ in ()).throw(
        KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        pl.Pipeline(cfg, out, progress=False).run()
    metrics = (out / "metrics.json").read_bytes()
    for argv in (["evaluate", out], ["report", out]):
        code, res = _run(argv, capsys)
        assert code == 2 and "points.ply came from an earlier config" in res.err, res.err
    assert (out / "metrics.json").read_bytes() == metrics


# --------------------------------------------------------------------------- 3: locks, options
_HOLD = """
import sys, time
from svolsdf.io.runfolder import folder_lock
with folder_lock(sys.argv[1], "svolsdf test-holder"):
    print("held", flush=True)
    time.sleep(60)
"""


def test_every_writer_refuses_a_folder_another_command_writes(field_run, scene, tmp_path,
                                                              capsys):
    out = _copy(field_run, tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = sorted(p.name for p in out.iterdir())
        for argv in (["evaluate", out], ["report", out], ["render", out, "--views", "0"],
                     ["reconstruct", "-o", out, "--config", out / "config.yaml"]):
            code, res = _run(argv, capsys)
            assert code == 2 and "another svolsdf run (svolsdf test-holder, pid" in res.err, (
                argv, res.err)
        assert sorted(p.name for p in out.iterdir()) == before
        mvs_out = tmp_path / "mvs"
        mvs_out.mkdir()
        holder2 = subprocess.Popen([sys.executable, "-c", _HOLD, str(mvs_out)],
                                   stdout=subprocess.PIPE, text=True)
        try:
            assert holder2.stdout.readline().strip() == "held"
            code, res = _run(["mvs", scene, "-o", mvs_out, "--views", "0", "1"], capsys)
            assert code == 2 and "another svolsdf run" in res.err
        finally:
            holder2.kill()
            holder2.wait()
    finally:
        holder.kill()
        holder.wait()


#: `svolsdf evaluate RUN --no-report` that, once it holds RUN's lock, says so and waits until the
#: file GATE exists: a first evaluation that is certainly still running when the second starts
_GATED_EVALUATE = """
import sys, time
from pathlib import Path
from svolsdf.cli import main
from svolsdf.evaluate import scoring

run, gate, real = sys.argv[1], Path(sys.argv[2]), scoring._evaluate_run

def gated(*args):  # called by evaluate_run inside folder_lock
    print("evaluating", flush=True)
    t0 = time.monotonic()
    while not gate.exists() and time.monotonic() - t0 < 120:
        time.sleep(0.02)
    return real(*args)

scoring._evaluate_run = gated
main(["evaluate", run, "--no-report"])
"""


def test_two_evaluations_at_once_one_is_refused(mvs_run, tmp_path):
    """Two evaluations of one folder at once: while the first holds the lock, the second is
    refused (exit 2, the lock's line naming the first's pid; docs/run-folder.md "One lock for
    every writer"), and the first then finishes and writes whole metrics. The first waits inside
    the lock until the second has been refused, so the two overlap on every machine (issue 50:
    two evaluations started together used to be allowed to run one after the other)."""
    import os

    import svolsdf

    out = _copy(mvs_run, tmp_path / "run")
    assert not (out / "metrics.json").exists()
    gate = tmp_path / "gate"
    env = dict(os.environ, PYTHONPATH=str(Path(svolsdf.__file__).parents[1]))
    first = subprocess.Popen([sys.executable, "-c", _GATED_EVALUATE, str(out), str(gate)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert first.stdout.readline().strip() == "evaluating", first.stderr.read()
        second = subprocess.run([sys.executable, "-m", "svolsdf", "evaluate", str(out),
                                 "--no-report"], capture_output=True, text=True, env=env,
                                timeout=300)
        assert second.returncode == 2, (second.returncode, second.stderr)
        assert f"another svolsdf run (svolsdf evaluate, pid {first.pid})" in second.stderr, \
            second.stderr
        assert not (out / "metrics.json").exists()  # the refused one wrote nothing
        gate.touch()
        _, err = first.communicate(timeout=300)
        assert first.returncode == 0, err
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert json.loads((out / "metrics.json").read_text())["chamfer"]
    assert not [p for p in out.iterdir() if ".tmp" in p.name]


@pytest.mark.parametrize("argv, msg", [
    (["evaluate", "RUN", "--scene", "NOWHERE"], "NOWHERE"),
    (["evaluate", "RUN", "--scene", "RUN"], "no known scene layout"),
    (["report", "RUN", "--scene", "NOWHERE"], "NOWHERE"),
    (["evaluate", "RUN", "--views", "99"], "no renders/<id>.png of view(s) [99]"),
    (["evaluate", "RUN", "--scan", "9"], "--scan 9: only the DTU and BlendedMVS protocols"),
])
def test_options_evaluate_and_report_cannot_honour_exit_2(mvs_run, tmp_path, capsys, argv, msg):
    out = _copy(mvs_run, tmp_path / "run")
    _main(["evaluate", out, "--no-report"])
    metrics = (out / "metrics.json").read_bytes()
    sub = {"RUN": str(out), "NOWHERE": str(tmp_path / "nowhere")}
    code, res = _run([sub.get(a, a) for a in argv], capsys)
    assert code == 2 and msg.replace("NOWHERE", str(tmp_path / "nowhere")) in res.err, res.err
    assert (out / "metrics.json").read_bytes() == metrics  # the good metrics stay


def test_report_on_an_empty_or_half_finished_folder_is_not_a_run(mvs_run, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    half = tmp_path / "half"
    half.mkdir()
    for name in ("config.yaml", "views.json", "stages.json"):
        shutil.copy(mvs_run / name, half / name)
    for folder in (empty, half):
        for cmd in ("report", "evaluate"):
            code, res = _run([cmd, folder], capsys)
            assert code == 2 and "not a run folder" in res.err
    assert list(empty.iterdir()) == [] and not (half / "report.html").exists()


def test_an_output_that_is_the_scene_or_another_commands_folder_is_refused(mvs_run, scene,
                                                                           tmp_path, capsys):
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    before = sorted(p.name for p in sc.rglob("*"))
    for argv in (["reconstruct", sc, "-o", sc], ["reconstruct", sc, "-o", sc / "run"],
                 ["reconstruct", sc, "-o", tmp_path], ["mvs", sc, "-o", sc]):
        code, res = _run(argv, capsys)
        assert code == 2 and "-o" in res.err, (argv, res.err)
    assert sorted(p.name for p in sc.rglob("*")) == before
    out = _copy(mvs_run, tmp_path / "run")
    points = (out / "points.ply").read_bytes()
    code, res = _run(["mvs", sc, "-o", out, "--views", "0", "1"], capsys)
    assert code == 2 and "a run of svolsdf reconstruct" in res.err
    assert (out / "points.ply").read_bytes() == points


def test_an_output_folder_holding_other_files_is_refused_and_runs_resume(mvs_run, field_run,
                                                                         scene, tmp_path, capsys):
    """Issue 50: reconstruct and mvs refuse a folder holding files that are not a svolsdf run
    (the user's notes.txt), in one line before any work, and leave it as it was; an earlier
    run's folder (resumed, even with the user's file beside it), one a run left before its
    views.json, a new and an empty folder keep working."""
    from svolsdf.io.runfolder import MVS_NAMES, RUN_NAMES
    from svolsdf.scene.checks import check_output_folder

    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "notes.txt").write_text("mine")
    for argv in (["reconstruct", scene, "-o", notes, "--mode", "mvs-only", "--no-progress"],
                 ["mvs", scene, "-o", notes, "--views", "0", "1"]):
        code, res = _run(argv, capsys)
        err = res.err.strip()
        assert code == 2 and len(err.splitlines()) == 1, err
        assert f"-o {notes}: that folder holds files that are not a svolsdf run (notes.txt)" \
            in err, err
    assert [p.name for p in notes.iterdir()] == ["notes.txt"]  # no lock, no log
    # an earlier run: resumed (every stage reused), the user's file beside it kept
    out = _copy(mvs_run, tmp_path / "run")
    (out / "notes.txt").write_text("mine")
    stages = (out / "stages.json").read_text()
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    assert (out / "stages.json").read_text() == stages and (out / "notes.txt").is_file()
    # a run stopped before views.json (its bookkeeping, a killed write's temporary) goes on
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    for name in (".svolsdf.lock", "log", ".stages.json.123.0a1b2c3d.tmp"):
        (stopped / name).write_text("")
    check_output_folder(stopped, scene, "svolsdf reconstruct")
    # a new folder and an empty one (a desktop's index file aside) take svolsdf mvs, and its own
    # output again
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / ".DS_Store").write_bytes(b"")
    for folder in (tmp_path / "new", empty, empty):
        _main(["mvs", scene, "-o", folder, "--views", "0", "1"])
        assert (folder / "mvs.json").is_file()
    # the names a run writes: every name of a finished run (evaluated, reported) and of an mvs
    # output is known, so that a folder the commands made is never taken for the user's
    full = _copy(field_run, tmp_path / "full")
    _main(["evaluate", full])
    names = {p.name for p in full.iterdir()}
    assert {"report.html", "metrics.json", "mesh.ply", "field"} <= names <= RUN_NAMES, names
    assert {p.name for p in empty.iterdir()} - {".DS_Store"} <= MVS_NAMES


# --------------------------------------------------------------------------- 4: degenerate input
def _bomb_png(path: Path) -> None:
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    path.write_bytes(b"\x89PNG\r\n\x1a\n"
                     + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 100)) + chunk(b"IEND", b""))


def _cameras(sc: Path, change) -> None:
    from svolsdf.scene.cameras import decompose_projection

    d = dict(np.load(sc / "cameras.npz"))
    c0 = None
    for i in range(4):
        K, w2c = (t.numpy() for t in decompose_projection(torch.from_numpy(d[f"world_mat_{i}"])))
        c = -w2c[:3, :3].T @ w2c[:3, 3]
        c0 = c if c0 is None else c0
        w2c = change(i, w2c.copy(), c0)
        P = np.eye(4)
        P[:3] = K @ w2c[:3]
        d[f"world_mat_{i}"] = P
    np.savez(sc / "cameras.npz", **d)


def _look_away(i, w2c, c0):
    return np.diag([-1.0, 1, -1, 1]) @ w2c if i == 1 else w2c


def _left_handed(i, w2c, c0):
    if i == 1:
        w2c[:3, :3] = -w2c[:3, :3]  # det R = -1
    return w2c


def _one_point(i, w2c, c0):
    w2c[:3, 3] = -w2c[:3, :3] @ c0
    return w2c


def _black_masks(sc: Path) -> None:
    for p in (sc / "mask").iterdir():
        Image.fromarray(np.zeros_like(np.array(Image.open(p)))).save(p)


@pytest.mark.parametrize("case, msg", [
    ("black masks", "object mask of view 0 is empty"),
    ("tiny", "reconstruction needs at least 16 pixels a side"),
    ("bomb", "000001.png: the image declares too many pixels"),
    ("mesh resolution", "mesh.resolution) = 100000"),
    ("look away", "view 1's camera does not see the scene's bounding region"),
    ("left-handed", "view 1's camera does not see the scene's bounding region"),
    ("one point", "all have their camera at one point"),
])
def test_degenerate_input_exits_2_before_any_stage_leaving_no_out(scene, tmp_path, capsys,
                                                                  case, msg):
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    extra = []
    if case == "black masks":
        _black_masks(sc)
    elif case == "tiny":
        extra = ["--size", "12x12"]
    elif case == "bomb":
        _bomb_png(sc / "image" / "000001.png")
    elif case == "mesh resolution":
        extra = ["--mesh-resolution", "100000"]
    else:
        _cameras(sc, {"look away": _look_away, "left-handed": _left_handed,
                      "one point": _one_point}[case])
    out = tmp_path / "out"
    code, res = _run(["reconstruct", sc, "-o", out, "--views", "0", "1", "2", *extra], capsys)
    assert code == 2 and msg in res.err and len(res.err.strip().splitlines()) == 1, res.err
    assert not out.exists()


def test_a_right_handed_check_of_explicit_rotations(scene):
    from svolsdf.scene.checks import check_scene
    from svolsdf.scene.loaders import load_scene

    s = load_scene(scene, load_images=False)
    check_scene(s)
    s.cameras.w2c[1, :3, :3] *= -1  # a mirror, as a transforms.json or cam.txt could hold
    with pytest.raises(InputError, match="view 1's camera is left-handed|rotation of view 1"):
        check_scene(s)


def test_synth_refuses_a_size_no_run_takes(tmp_path, capsys):
    code, res = _run(["synth", tmp_path / "s", "--size", "8x8"], capsys)
    assert code == 2 and "at least 16x16" in res.err and not (tmp_path / "s").exists()


def test_a_run_that_fuses_no_point_exits_2_saying_why(mvs_run, scene, tmp_path, capsys,
                                                      monkeypatch):
    import svolsdf.pipeline.fusion_stage as pf

    monkeypatch.setattr(pf, "fuse", lambda p, path: (path.write_bytes(b"") and 0) or (0, {}))
    out = tmp_path / "run"
    code, res = _run(["reconstruct", scene, "-o", out, "--mode", "mvs-only", "--views", "0",
                      "1", "2", "--no-progress"], capsys)
    assert code == 2 and "fusion kept no point" in res.err and "--views auto" in res.err
    assert not (out / "points.ply").exists() and "fusion" not in json.loads(
        (out / "stages.json").read_text())


def test_disk_full_names_the_file_and_leaves_no_temporary(mvs_run, tmp_path, capsys,
                                                          monkeypatch):
    out = _copy(mvs_run, tmp_path / "run")
    real = np.save

    def full(file, *a, **k):
        if "depth" in str(file) and "stage" not in str(file):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(file, *a, **k)

    monkeypatch.setattr(np, "save", full)
    from svolsdf.pipeline.rundir import save_npy

    with pytest.raises(InputError, match="depth/7.npy: cannot write it, the disk is full"):
        save_npy(out / "depth" / "7.npy", np.zeros(3))
    # evaluate's and report's files: the same, through the one atomic writer
    monkeypatch.setattr(Path, "write_text", lambda self, *a, **k: (_ for _ in ()).throw(
        OSError(errno.ENOSPC, "No space left on device")))
    code, res = _run(["evaluate", out, "--no-report"], capsys)
    assert code == 2 and "metrics.json: cannot write it, the disk is full" in res.err, res.err
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


def test_temporary_names_are_unique(tmp_path):
    from svolsdf.io.runfolder import unique_temp

    names = {unique_temp(tmp_path / "metrics.json").name for _ in range(20)}
    assert len(names) == 20 and all(n.startswith(".metrics.json.") for n in names)


def test_colmap_log_files_go_to_the_given_folder(tmp_path):
    pytest.importorskip("pycolmap")
    code = f"""
import pycolmap
from pathlib import Path
from svolsdf.calibrate.sfm import _colmap_log_files
_colmap_log_files(pycolmap, Path({str(tmp_path / 'logs')!r}))
pycolmap.logging.warning("written to the scene's folder")
_colmap_log_files(pycolmap, None)
pycolmap.logging.warning("written to no file")
"""
    env = {**__import__("os").environ, "GLOG_log_dir": str(tmp_path / "default")}
    (tmp_path / "default").mkdir()
    subprocess.run([sys.executable, "-c", code], check=True, env=env, capture_output=True)
    files = list((tmp_path / "logs").iterdir())
    assert files and "written to the scene's folder" in files[0].read_text()
    assert not list((tmp_path / "default").iterdir())  # glog's default folder gets nothing
