"""The `svolsdf` command: reconstruct/demo wiring and one-line errors (exit 2) for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from svolsdf.cli import join_list_options, main
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
    assert join_list_options(["reconstruct", "S", "--views", "25", "22", "28", "-o", "X"]) == [
        "reconstruct", "S", "--views", "25 22 28", "-o", "X"]
    assert join_list_options(["x", "--views", "1,2", "OUT"]) == ["x", "--views", "1,2", "OUT"]


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


def test_background_flag_reaches_the_config(monkeypatch, tmp_path):
    # the flag sets field.background; the pipeline is replaced by a recorder (no run)
    import svolsdf.pipeline as pl

    seen = {}

    class Recorder:
        def __init__(self, cfg, out, progress=True):
            seen["cfg"] = cfg

        def run(self):
            return {"points": "p", "mesh": None, "timing": {}}

    monkeypatch.setattr(pl, "Pipeline", Recorder)
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
    assert f"report {report}" in capsys.readouterr().out.splitlines()[-1]
    page = report.read_text()
    assert "<h2>3D view" in page and "Chamfer overall (points)" in page
    assert json.loads((report.parent / "metrics.json").read_text())["chamfer"]["overall"] < 1


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
    pytest.importorskip("pycolmap", reason="svolsdf calibrate needs pycolmap")
    code, out = _run(["calibrate", str(tmp_path / "none"), "-o", str(tmp_path / "S")], capsys)
    assert code == 2 and "does not exist" in out.err and len(out.err.strip().splitlines()) == 1
    code, out = _run(["calibrate", str(tmp_path), "-o", str(tmp_path / "S"), "--matcher", "x"],
                     capsys)
    assert code == 2 and "unknown matcher" in out.err
