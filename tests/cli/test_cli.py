"""The `svolsdf` command: reconstruct/demo wiring and one-line errors (exit 2) for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from svolsdf.cli import expand_list_options, main
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli") / "scene"
    make_synthetic_scene(d, SynthConfig(views=3, width=64, height=48, seed=2, supersample=1,
                                        gt_points=5000))
    return d


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    return e.value.code, capsys.readouterr()


def test_views_list_is_joined():
    assert expand_list_options(["reconstruct", "S", "--views", "25", "22", "28", "-o", "X"]) == [
        "reconstruct", "S", "--views", "25 22 28", "-o", "X"]
    assert expand_list_options(["x", "--views", "1,2", "OUT"]) == ["x", "--views", "1,2", "OUT"]
    assert expand_list_options(["x", "--views=1", "2", "OUT"]) == ["x", "--views", "1 2", "OUT"]


def test_scene_lists_repeat_the_option_and_keep_each_argument_whole():
    # a quoted path with spaces is one scene, never split; several values repeat the option
    assert expand_list_options(["benchmark", "--scenes", "/d/my scans/scan 1", "b", "-o", "O"]
                               ) == ["benchmark", "--scenes", "/d/my scans/scan 1", "--scenes",
                                     "b", "-o", "O"]
    assert expand_list_options(["benchmark", "--scenes=a b", "c", "--scenes", "d"]) == [
        "benchmark", "--scenes", "a b", "--scenes", "c", "--scenes", "d"]
    assert expand_list_options(["benchmark", "--scenes"]) == ["benchmark", "--scenes"]


def test_bad_inputs_exit_2_with_one_line(scene, tmp_path, capsys):
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), "--views", "0", "1",
                      "7"], capsys)
    assert code == 2 and "7" in out.err and len(out.err.strip().splitlines()) == 1
    f = tmp_path / "file"
    f.write_text("x")
    code, out = _run(["reconstruct", str(scene), "-o", str(f)], capsys)
    assert code == 2 and "not a folder" in out.err
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  stepz: 3\n")
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o2"), "--config",
                      str(bad)], capsys)
    assert code == 2 and "stepz" in out.err
    code, out = _run(["reconstruct", str(tmp_path / "nope"), "-o", str(tmp_path / "o3")], capsys)
    assert code == 2 and "nope" in out.err
    # usage errors: click's message and exit code 2, not a traceback
    code, out = _run(["mvs", str(scene), "--bogus"], capsys)
    assert code == 2 and "No such option: --bogus" in out.err and "Traceback" not in out.err
    code, out = _run(["reconstruct", str(scene), "--steps", "abc"], capsys)
    assert code == 2 and "--steps" in out.err and "Traceback" not in out.err


def test_reconstruct_mvs_only_and_config_roundtrip(scene, tmp_path, capsys):
    out = tmp_path / "run"
    main(["reconstruct", str(scene), "-o", str(out), "--mode", "mvs-only", "--views", "0", "1",
          "2", "--no-progress"])
    assert (out / "points.ply").is_file() and not (out / "mesh.ply").exists()
    assert json.loads((out / "views.json").read_text())["inputs"] == [0, 1, 2]
    # the written config reruns the same job (all stages reused)
    main(["reconstruct", "-o", str(out), "--config", str(out / "config.yaml"), "--no-progress"])
    assert "reconstruct" not in capsys.readouterr().err


def test_background_flag_reaches_the_config(seen, tmp_path):
    # the flag sets field.background
    for flag, want in (("--background", True), ("--no-background", False), (None, False)):
        argv = ["reconstruct", str(tmp_path), "-o", str(tmp_path / "o")] + ([flag] if flag else [])
        seen.clear()
        main(argv)  # standalone_mode=False: returns normally on success
        assert seen["cfg"].field.background is want


def test_demo_ends_with_the_report(monkeypatch, tmp_path, capsys):
    # the reconstruction is replaced by a stand-in that writes the ground truth as its result
    import svolsdf.pipeline as pl
    from svolsdf.io.ply import read_ply, write_mesh_ply, write_points_ply

    class GroundTruthRun:
        def __init__(self, cfg, out, progress=True):
            self.scene, self.out = Path(cfg.scene.path), Path(out)

        def run(self):
            self.out.mkdir(parents=True)
            gt = read_ply(self.scene / "gt_points.ply")["points"]
            write_points_ply(self.out / "points.ply", gt[::4])
            m = read_ply(self.scene / "gt_mesh.ply")
            write_mesh_ply(self.out / "mesh.ply", m["points"], m["faces"])
            (self.out / "views.json").write_text(json.dumps(
                {"inputs": [0, 1, 2], "scene": str(self.scene)}))
            (self.out / "config.yaml").write_text(f"scene:\n  path: {self.scene}\n")
            return {"points": str(self.out / "points.ply"), "mesh": str(self.out / "mesh.ply"),
                    "timing": {"total": {"seconds": 1.0}}}

    monkeypatch.setattr(pl, "Pipeline", GroundTruthRun)
    main(["demo", "-o", str(tmp_path / "demo"), "--size", "64x48"])
    report = tmp_path / "demo" / "run" / "report.html"
    printed = capsys.readouterr().out
    assert f"report {report}" in printed.splitlines()[-1]
    # its Chamfer says which protocol it follows (not the one --gt-points would give)
    assert "Chamfer protocol: the synthetic scene's own ground truth, only the part" in printed
    page = report.read_text()
    assert "<h2>3D view" in page and "Chamfer overall (points)" in page
    assert json.loads((report.parent / "metrics.json").read_text())["chamfer"]["overall"] < 1


# --------------------------------------------------------------------------- issue 29's cases
#: a seconds-long run of the 64x48 scene: a 16^3 grid, 32 rays, a checkpoint every 10 steps
SMALL = ("field: {grid_start_resolution: 16, grid_resolution: 16}\n"
         "mesh: {resolution: 24}\nfusion: {unguided: false}\n"
         "train: {rays: 32, checkpoint_every: 10, steps: STEPS}\n")


def _small_config(tmp_path, scene, steps=30):
    p = tmp_path / "small.yaml"
    p.write_text(f"scene: {{path: {scene}}}\n" + SMALL.replace("STEPS", str(steps)))
    return p


@pytest.fixture(scope="module")
def small_run(scene, tmp_path_factory):
    """A finished run of the small config (points, mesh, field/model.pt)."""
    d = tmp_path_factory.mktemp("small")
    out = d / "run"
    main(["reconstruct", "-o", str(out), "--config", str(_small_config(d, scene)),
          "--no-progress"])
    return out


def _copy_run(src, dest):
    import shutil

    shutil.copytree(src, dest, ignore=shutil.ignore_patterns(".svolsdf.lock"))
    return dest


def _stages(out):
    return json.loads((out / "stages.json").read_text())


@pytest.mark.slow  # a real process: ~15 s
def test_ctrl_c_exits_130_naming_the_stage_and_a_rerun_resumes(scene, tmp_path):
    # a real process and a real SIGINT during the optimization
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    import svolsdf

    out = tmp_path / "run"
    # enough steps that the signal, sent once the first checkpoint exists, finds the
    # optimization still running on a fast or a busy machine (30 steps could end before it
    # arrived)
    cfg = _small_config(tmp_path, scene, steps=1000)
    # one torch thread: on two busy cores the run's threads could starve this process's
    # polling until the optimization had ended (threads enters no stage key: the rerun resumes)
    cfg.write_text(cfg.read_text() + "threads: 1\n")
    env = dict(os.environ, PYTHONPATH=str(Path(svolsdf.__file__).parents[1]))
    p = subprocess.Popen([sys.executable, "-m", "svolsdf", "reconstruct", "-o", str(out),
                          "--config", str(cfg), "--no-progress"], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         # a shell's background job (CI started with &) ignores SIGINT, and
                         # its children inherit that: give the run the default, as a terminal
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    while not (out / "field" / "checkpoint.pt").is_file() and p.poll() is None:
        assert time.monotonic() - t0 < 120, "no checkpoint in 2 minutes"
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("interrupted: stage field stopped at step ") and "rerun" in last
    assert "Traceback" not in err
    assert last in (out / "log").read_text()  # the line is in OUT/log too
    assert "field" not in _stages(out) and "mvs1" in _stages(out)
    # the rerun resumes: stage 1 reused, the optimization continued from its checkpoint
    main(["reconstruct", "-o", str(out), "--config", str(cfg), "--no-progress"])
    log = (out / "log").read_text()
    assert "resumed from" in log and (out / "mesh.ply").is_file()
    assert {"field", "mesh"} <= set(_stages(out))


def test_an_interrupt_anywhere_exits_130_with_one_line(monkeypatch, tmp_path, capsys):
    # typer turns Ctrl-C into exit status 130; main once dropped it (exit 0, no message)
    import svolsdf.scene.synthetic as synthetic

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(synthetic, "make_synthetic_scene", stop)
    code, out = _run(["synth", str(tmp_path / "s"), "--size", "32x24"], capsys)
    assert code == 130 and out.err.strip() == "interrupted"


def test_an_interrupt_as_the_command_ends_exits_130_with_one_line(monkeypatch, tmp_path,
                                                                   capsys):
    # Ctrl-C after the command returned, while main restores the SIGTERM handler
    import svolsdf.cli as cli

    real, calls = cli.signal.signal, []

    def late(signum, handler):
        if signum == cli.signal.SIGTERM:  # (SIGINT's handler is svolsdf.errors')
            calls.append(signum)
            if len(calls) == 2:  # the restore in main's finally
                raise KeyboardInterrupt
        return real(signum, handler)

    monkeypatch.setattr(cli.signal, "signal", late)
    try:
        code, out = _run(["synth", str(tmp_path / "s"), "--size", "32x24"], capsys)
    except KeyboardInterrupt:
        pytest.fail("the interrupt escaped main (a traceback for the user)")
    finally:
        monkeypatch.undo()
    assert len(calls) == 2 and code == 130 and out.err.strip().endswith("interrupted")
    assert "Traceback" not in out.err


@pytest.mark.parametrize("views, repeated", [("0 1 1", "1"), ("2 2", "2")])
def test_repeated_view_ids_exit_2_naming_the_id(scene, tmp_path, capsys, views, repeated):
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), "--views",
                      *views.split()], capsys)
    assert code == 2 and f"view {repeated} is given twice" in out.err
    assert len(out.err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
    # from a config file too, and for a library caller of load_scene
    from svolsdf.scene import SceneError, load_scene

    (tmp_path / "c.yaml").write_text(f"scene: {{views: [{views.replace(' ', ', ')}]}}\n")
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), "--config",
                      str(tmp_path / "c.yaml")], capsys)
    assert code == 2 and f"({repeated} is repeated)" in out.err
    with pytest.raises(SceneError, match=f"view id {repeated} is given more than once"):
        load_scene(scene, views=[int(v) for v in views.split()], load_images=False)


def test_zero_world_mat_exits_2_naming_file_and_key(scene, tmp_path, capsys):
    import shutil

    import numpy as np

    bad = tmp_path / "scene"
    shutil.copytree(scene, bad)
    cams = dict(np.load(bad / "cameras.npz"))
    cams["world_mat_1"] = np.zeros((4, 4))
    np.savez(bad / "cameras.npz", **cams)
    code, out = _run(["reconstruct", str(bad), "-o", str(tmp_path / "o")], capsys)
    assert code == 2 and "cameras.npz: world_mat_1:" in out.err and "singular" in out.err
    assert len(out.err.strip().splitlines()) == 1


def test_unwritable_output_folders_exit_2(scene, tmp_path, capsys, monkeypatch):
    import os
    import sys
    from pathlib import Path

    if sys.platform.startswith("linux") and Path("/sys/kernel").is_dir():
        for argv in (["reconstruct", str(scene), "-o", "/sys/svolsdf-test-out"],
                     ["reconstruct", str(scene), "-o", "/sys/kernel"],
                     ["synth", "/sys/svolsdf-test-scene", "--size", "32x24"]):
            code, out = _run(argv, capsys)
            assert code == 2 and "cannot write" in out.err, (argv, out.err)
            assert "Traceback" not in out.err and len(out.err.strip().splitlines()) == 1
    # a read-only mount: writing the probe file fails with EROFS (root ignores permission
    # bits, so a chmod cannot stand in for it)
    import errno
    import tempfile

    def read_only(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    for argv in (["reconstruct", str(scene), "-o", str(tmp_path / "ro")],
                 ["synth", str(tmp_path / "ro_scene"), "--size", "32x24"]):
        code, out = _run(argv, capsys)
        assert code == 2 and "Read-only file system" in out.err, out.err


@pytest.mark.parametrize("argv, key", [
    (["--steps", "-5"], "--steps (train.steps) = -5"),
    (["--threads", "-2"], "--threads (threads) = -2"),
    (["--mode", "fast"], "--mode (train.mode) = 'fast'"),
    (["--device", "gpu"], "--device (device) = 'gpu'"),
    (["--mvs-scale", "0"], "--mvs-scale (mvs.scale) = 0.0"),
])
def test_bad_option_values_exit_2_before_any_work(scene, tmp_path, capsys, argv, key):
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), *argv], capsys)
    assert code == 2 and out.err.startswith(f"error: {key}: expected"), out.err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, key", [
    ("train: {steps: fifty}", "train.steps = 'fifty'"),
    ("train: {lr: abc}", "train.lr = 'abc'"),
    ("scene: {image_size: 160x120}", "scene.image_size = '160x120'"),
    ("scene: {views: '0 1 2'}", "scene.views = '0 1 2'"),
    ("scene: {use_masks: 'no'}", "scene.use_masks = 'no'"),
    ("train: {rays: -4}", "train.rays = -4"),
])
def test_bad_config_values_exit_2_before_any_work(scene, tmp_path, capsys, text, key):
    (tmp_path / "c.yaml").write_text(text + "\n")
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), "--config",
                      str(tmp_path / "c.yaml")], capsys)
    assert code == 2 and f"c.yaml: {key}: expected" in out.err, out.err
    assert not (tmp_path / "o").exists()  # before stage 1, before the folder


def test_corrupt_model_render_exits_2_reconstruct_trains_again(small_run, tmp_path, capsys):
    out = _copy_run(small_run, tmp_path / "run")
    model = out / "field" / "model.pt"
    model.write_bytes(model.read_bytes()[:200])  # truncated
    code, res = _run(["render", str(out), "--views", "0"], capsys)
    assert code == 2 and "model.pt" in res.err and "Traceback" not in res.err
    assert len(res.err.strip().splitlines()) == 1
    main(["reconstruct", "-o", str(out), "--config", str(out / "config.yaml"), "--no-progress"])
    log = (out / "log").read_text()
    # found by the size its stage recorded (a folder without the record: "could not be read")
    assert "model.pt has 200 bytes" in log and "running the stage field again" in log
    import torch

    assert "model_state_dict" in torch.load(model, weights_only=False)
    assert {"field", "guide", "mesh"} <= set(_stages(out))


def test_corrupt_checkpoint_is_discarded_and_the_optimization_restarts(small_run, tmp_path):
    out = _copy_run(small_run, tmp_path / "run")
    # as after a kill during the optimization: its checkpoint, no finished field
    st = _stages(out)
    (out / "stages.json").write_text(json.dumps({k: v for k, v in st.items()
                                                 if k in ("mvs1", "field_partial")}))
    (out / "field" / "model.pt").unlink()
    (out / "field" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    main(["reconstruct", "-o", str(out), "--config", str(out / "config.yaml"), "--no-progress"])
    log = (out / "log").read_text()
    assert "checkpoint.pt could not be read" in log and "resumed from" not in log
    # the run's outputs say it too (timing.json, copied into metrics.json and the report)
    why = json.loads((out / "timing.json").read_text())["field"]["rerun"]
    assert why.startswith(f"{out / 'field' / 'checkpoint.pt'} could not be read"), why
    assert (out / "field" / "model.pt").is_file() and {"field", "mesh"} <= set(_stages(out))


def test_a_failed_run_writes_its_error_to_out_log(scene, tmp_path, capsys):
    import shutil

    bad = tmp_path / "scene"
    shutil.copytree(scene, bad)
    img = sorted((bad / "image").iterdir())[1]
    img.write_bytes(b"not a png")
    out = tmp_path / "o"
    out.mkdir()  # an existing output folder keeps the error in its log
    code, res = _run(["reconstruct", str(bad), "-o", str(out), "--views", "0", "1", "2"], capsys)
    assert code == 2 and img.name in res.err
    line = res.err.strip().removeprefix("error: ")
    assert f"ERROR svolsdf.pipeline: error: {line}" in (out / "log").read_text()
    # a new one is not left behind (issue 42)
    code, res = _run(["reconstruct", str(bad), "-o", str(tmp_path / "new"), "--views", "0", "1",
                      "2"], capsys)
    assert code == 2 and img.name in res.err and not (tmp_path / "new").exists()


@pytest.mark.parametrize("argv, msg", [
    (["render", "RUN", "--chunk", "0"], "--chunk 0"),
    (["render", "RUN", "--views", "1", "1"], "view 1 is given twice"),
    (["evaluate", "RUN", "--threshold", "-1"], "--threshold -1.0"),
    (["evaluate", "RUN", "--ssim-data-range", "0"], "--ssim-data-range 0.0"),
    (["evaluate", "RUN", "--lpips-net", "squeeze"], "--lpips-net 'squeeze'"),
])
def test_bad_render_and_evaluate_options_exit_2(small_run, capsys, argv, msg):
    before = sorted(p.name for p in small_run.iterdir())
    code, out = _run([str(small_run) if a == "RUN" else a for a in argv], capsys)
    assert code == 2 and msg in out.err and len(out.err.strip().splitlines()) == 1, out.err
    assert sorted(p.name for p in small_run.iterdir()) == before


def test_sigterm_stops_a_run_with_status_143_and_the_stage(scene, tmp_path, capsys,
                                                           monkeypatch):
    import os
    import signal
    import time

    from svolsdf.pipeline.stages.mvs1 import MVS1

    def terminated(self, ctx, inputs):
        os.kill(os.getpid(), signal.SIGTERM)  # as `kill PID` would, during stage 1
        time.sleep(30)

    monkeypatch.setattr(MVS1, "run", terminated)
    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "o"
    code, res = _run(["reconstruct", str(scene), "-o", str(out), "--no-progress"], capsys)
    assert code == 143
    assert res.err.strip().splitlines()[-1].startswith("interrupted: stage mvs1 stopped")
    assert "stage mvs1 stopped" in (out / "log").read_text()
    assert signal.getsignal(signal.SIGTERM) == before  # main restores the handler


@pytest.mark.parametrize("argv, msg", [
    (["--weights", "w.pt"], "takes no weights"),  # the plane sweep has none
    (["--backbone", "casmvsnet"], "needs --weights"),
    (["--fusion-network", "nope.pt"], "nope.pt"),
])
def test_backbone_options_fail_before_the_output_folder(scene, tmp_path, capsys, argv, msg):
    code, out = _run(["reconstruct", str(scene), "-o", str(tmp_path / "o"), *argv], capsys)
    assert code == 2 and msg in out.err and not (tmp_path / "o").exists(), out.err


def test_demo_checks_its_options_before_rendering_a_scene(tmp_path, capsys):
    code, out = _run(["demo", "-o", str(tmp_path / "d"), "--steps", "-1"], capsys)
    assert code == 2 and "--steps (train.steps) = -1" in out.err
    assert not (tmp_path / "d").exists()


def test_unreadable_bookkeeping_files_do_not_stop_render_evaluate_or_a_rerun(small_run,
                                                                             tmp_path):
    out = _copy_run(small_run, tmp_path / "run")
    for name in ("views.json", "timing.json", "stages.json"):
        (out / name).write_text("{not json")
    main(["render", str(out), "--views", "0"])
    assert (out / "renders" / "0.png").is_file()
    main(["evaluate", str(out), "--no-report"])
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer"]["overall"] is not None or m["images"]["psnr"]["mean"] is not None
    # stages.json unreadable: every stage runs again, with a warning
    main(["reconstruct", "-o", str(out), "--config", str(out / "config.yaml"), "--no-progress"])
    assert "stages.json is unreadable" in (out / "log").read_text()
    assert {"mvs1", "field", "mesh"} <= set(_stages(out))


def test_read_only_run_folder_render_and_evaluate_exit_2_before_work(small_run, capsys,
                                                                     monkeypatch):
    import errno
    import os
    import tempfile

    def read_only(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    before = sorted(p.name for p in small_run.iterdir())
    for argv in (["render", str(small_run), "--views", "0"], ["evaluate", str(small_run)]):
        code, out = _run(argv, capsys)
        assert code == 2 and "Read-only file system" in out.err, out.err
    assert sorted(p.name for p in small_run.iterdir()) == before


def test_views_auto_reaches_the_config_and_is_reported(monkeypatch, tmp_path, capsys):
    import svolsdf.pipeline as pl

    seen = {}

    class Recorder:
        def __init__(self, cfg, out, progress=True):
            seen["cfg"] = cfg
            self.views, self.all_view_ids = [4, 3, 5], list(range(9))

        def load(self):
            seen["loaded"] = True

        def run(self):
            return {"points": "p", "mesh": None, "timing": {}}

    monkeypatch.setattr(pl, "Pipeline", Recorder)
    for argv, n in ((["--views", "auto"], 3), (["--views", "auto", "5"], 5)):
        main(["reconstruct", str(tmp_path), "-o", str(tmp_path / "o")] + argv)
        sc = seen["cfg"].scene
        assert sc.view_selection == "auto" and sc.num_views == n and not sc.views
        assert "views auto: picked [4, 3, 5] of 9 views" in capsys.readouterr().out
    # auto also replaces the views a --config file lists
    c = tmp_path / "c.yaml"
    c.write_text("scene: {views: [0, 1, 2]}\n")
    main(["reconstruct", str(tmp_path), "-o", str(tmp_path / "o"), "--config", str(c),
          "--views", "auto"])
    assert seen["cfg"].scene.views is None and seen["cfg"].scene.view_selection == "auto"
    code, out = _run(["reconstruct", str(tmp_path), "--views", "auto,x"], capsys)
    assert code == 2 and "auto [N]" in out.err


def test_calibrate_maps_its_options(monkeypatch, tmp_path, capsys):
    import svolsdf.calibrate as cal

    seen = {}

    def fake(inputs, out, cfg):
        seen.update(inputs=inputs, out=out, cfg=cfg)
        return {"num_inputs": 12, "registered": ["a"] * 11, "unregistered": ["z.jpg"],
                "video": False, "size": [800, 600], "shared_camera": True,
                "matcher": cfg.matcher, "mean_reprojection_error_px": 0.5,
                "seconds": {"total": 3.0}}

    monkeypatch.setattr(cal, "calibrate", fake)
    main(["calibrate", str(tmp_path), "-o", str(tmp_path / "S"), "--max-size", "800",
          "--matcher", "sequential", "--no-progress"])
    cfg = seen["cfg"]
    assert cfg.max_size == 800 and cfg.matcher == "sequential" and not cfg.progress
    out = capsys.readouterr().out
    assert "registered 11 of 12 photos" in out and "not registered: z.jpg" in out
    assert "--views auto" in out


def test_calibrate_errors_exit_2_with_one_line(tmp_path, capsys):
    code, out = _run(["calibrate", str(tmp_path / "none"), "-o", str(tmp_path / "S")], capsys)
    assert code == 2 and "does not exist" in out.err and len(out.err.strip().splitlines()) == 1
    code, out = _run(["calibrate", str(tmp_path), "-o", str(tmp_path / "S"), "--matcher", "x"],
                     capsys)
    assert code == 2 and "unknown matcher" in out.err


def test_set_reaches_any_option_and_is_applied_last(seen, tmp_path, capsys):
    # --set section.option=value (YAML values), applied after the flags
    main(["reconstruct", str(tmp_path), "-o", str(tmp_path / "o"), "--steps", "50",
          "--set", "train.steps=70", "--set", "mesh.method=poisson",
          "--set", "mvs.ndepths=[64, 16, 8]", "--set", "fusion.network_weights=null"])
    c = seen["cfg"]
    assert (c.train.steps, c.mesh.method, c.mvs.ndepths) == (70, "poisson", [64, 16, 8])
    assert c.fusion.network_weights is None
    for item, msg in (("train.stepz=3", "did you mean train.steps"),
                      ("mesh.method=poison", "'field', 'poisson'"),
                      ("steps", "expected section.option=value")):
        with pytest.raises(SystemExit) as e:
            main(["reconstruct", str(tmp_path), "-o", str(tmp_path / "o"), "--set", item])
        err = capsys.readouterr().err
        assert e.value.code == 2 and msg in err and len(err.strip().splitlines()) == 1, err


def test_config_prints_every_option_with_its_doc(tmp_path, capsys):
    import yaml

    from svolsdf.config import config_from_dict, option_docs, preset

    for name in ("fast", "paper"):
        main(["config", "--preset", name])
        text = capsys.readouterr().out
        assert config_from_dict(yaml.safe_load(text)) == preset(name)  # loads back
        docs = option_docs()
        assert all(docs.values()), [k for k, v in docs.items() if not v]  # every option
        lines = text.splitlines()
        for key in ("train.steps", "mesh.method"):  # the doc comment sits above the key
            at = next(i for i, ln in enumerate(lines) if ln.startswith(f"  {key.split('.')[1]}:"))
            above = " ".join(ln.strip("# ") for ln in lines[:at][-6:])
            assert docs[key].split(".")[0][:40] in " ".join(above.split()), (key, above)
    main(["config", "--set", "train.steps=12"])
    assert "  steps: 12" in capsys.readouterr().out


def test_config_with_a_file_and_a_preset_behaves_as_reconstruct(tmp_path, capsys):
    """`svolsdf config --config FILE --preset P` once printed FILE and dropped P in silence:
    as reconstruct, a P that contradicts the file's preset is refused in one line, and the
    file's own preset named again shows the file."""
    main(["config", "--preset", "fast", "--set", "train.steps=12"])
    f = tmp_path / "mine.yaml"
    f.write_text(capsys.readouterr().out)
    main(["config", "--config", str(f), "--preset", "fast"])
    assert "  steps: 12" in capsys.readouterr().out
    errors = []
    for cmd in (["config"], ["reconstruct", str(tmp_path), "-o", str(tmp_path / "o")]):
        with pytest.raises(SystemExit) as e:
            main([*cmd, "--config", str(f), "--preset", "paper"])
        err = capsys.readouterr().err
        assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"--preset paper contradicts {f} (preset fast)" in err
        errors.append(err)
    assert errors[0] == errors[1]
    assert not (tmp_path / "o").exists()
