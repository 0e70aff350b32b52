"""Tests of svolsdf.commands.benchmark: the Table-1 writers (pure functions), the driver with a
stand-in pipeline on a tiny synthetic scene, the CLI, and one real mvs-only run."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import shared_path
from svolsdf.cli import main
from svolsdf.commands.benchmark import (
    BenchmarkConfig,
    benchmark_csv,
    benchmark_markdown,
    run_benchmark,
    scan_number,
)
from svolsdf.errors import InputError
from svolsdf.evaluate.benchmark_tables import method_label
from svolsdf.io.ply import read_ply, write_points_ply

# --------------------------------------------------------------------------- pure table writers


def _row(scene, mode, acc, comp, psnr=None, t=10.0, status="ok"):
    return {"scene": scene, "mode": mode, "accuracy": acc, "completeness": comp,
            "overall": None if acc is None else (acc + comp) / 2, "psnr": psnr, "time_s": t,
            "status": status, "protocol": "generic"}


ROWS = [
    _row("scan24", "svolsdf", 1.0, 2.0, psnr=20.0, t=100),
    _row("scan24", "mvs-only", 2.0, 4.0, t=10),
    _row("scan37", "svolsdf", 3.0, 1.0, psnr=22.0, t=300),
    _row("scan37", "mvs-only", None, None, t=None, status="failed: RuntimeError: boom"),
]


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_markdown_table_values_mean_and_marks():
    md = benchmark_markdown(ROWS, ["svolsdf", "mvs-only"], title="T")
    lines = md.splitlines()
    assert lines[0] == "# T"
    # rows without a field kind (made before it was recorded) say so
    assert lines[2] == "Methods: svolsdf = S-VolSDF; mvs-only = MVS only."
    head = _cells(lines[4])
    assert head == ["scene", "svolsdf Acc.", "svolsdf Comp.", "svolsdf Chamfer", "svolsdf PSNR",
                    "svolsdf time (s)", "mvs-only Acc.", "mvs-only Comp.", "mvs-only Chamfer",
                    "mvs-only PSNR", "mvs-only time (s)"]
    r24 = _cells(lines[6])
    assert r24 == ["scan24", "1.00", "2.00", "**1.50**", "20.00", "100", "2.00", "4.00", "3.00",
                   "-", "10"]
    r37 = _cells(lines[7])
    assert r37 == ["scan37", "3.00", "1.00", "2.00", "22.00", "300", "-", "-", "-", "-", "-"]
    mean = _cells(lines[8])
    # svolsdf: mean over both scenes; mvs-only: only scan24 has values -> marked with *.
    assert mean == ["**mean**", "2.00", "1.50", "**1.75**", "21.00", "200", "2.00*", "4.00*",
                    "3.00*", "-", "10*"]
    assert "- scan37 / mvs-only: failed: RuntimeError: boom" in md


def test_markdown_without_psnr_has_no_psnr_columns_and_csv_matches():
    rows = [_row("a", "svolsdf", 0.5, 0.7), _row("b", "svolsdf", 0.25, 0.5)]
    md = benchmark_markdown(rows)
    assert "PSNR" not in md
    text = benchmark_csv(rows)
    table = list(csv.reader(io.StringIO(text)))
    assert table[0] == ["scene", "svolsdf_accuracy", "svolsdf_completeness", "svolsdf_overall",
                        "svolsdf_time_s"]
    assert [r[0] for r in table[1:]] == ["a", "b", "mean"]
    assert float(table[3][1]) == pytest.approx(0.375)
    assert float(table[3][3]) == pytest.approx((0.6 + 0.375) / 2)
    full = list(csv.reader(io.StringIO(benchmark_csv(ROWS, ["svolsdf", "mvs-only"]))))
    assert full[0][4] == "svolsdf_psnr" and full[2][6:] == ["", "", "", "", ""]
    with pytest.raises(InputError, match="no runs"):
        benchmark_markdown([])


def test_methods_are_named_for_what_they_are():
    """Issue 38: --mode volsdf with the grid field is not the paper's VolSDF."""
    rows = [{**_row("a", "volsdf", 1.0, 2.0), "field": "grid"},
            {**_row("a", "svolsdf", 0.5, 0.7), "field": "grid"}]
    md = benchmark_markdown(rows, ["svolsdf", "volsdf"])
    assert "volsdf = VolSDF (grid field, no prior)" in md and "svolsdf = S-VolSDF;" in md
    mlp = [{**r, "field": "mlp"} for r in rows]
    assert "volsdf = VolSDF (MLP)" in benchmark_markdown(mlp, ["volsdf"])
    mixed = benchmark_markdown(rows + [{**_row("b", "volsdf", 1.0, 1.0), "field": "mlp"}])
    assert "volsdf = VolSDF (grid field, no prior) / VolSDF (MLP)" in mixed
    assert "VolSDF (field kind not recorded)" in benchmark_markdown(
        [_row("a", "volsdf", 1.0, 2.0)])
    assert method_label("mvs-only") == "MVS only"


def test_scan_number_from_names():
    assert scan_number("/data/dtu_scan65") == 65
    assert scan_number("scan_24") == 24 and scan_number("Scan114") == 114
    assert scan_number("/data/scan65/synthetic") is None


# --------------------------------------------------------------------------- driver


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    root = tmp_path_factory.mktemp("bench") / "synth_a"
    return make_synthetic_scene(root, SynthConfig(views=4, width=96, height=72, gt_points=4000,
                                                  supersample=1, mesh_resolution=6.0))


class FakePipeline:
    """Stands in for svolsdf.pipeline.Pipeline: writes what the real one writes that the
    benchmark reads (points.ply, views.json, config.yaml, timing.json), plus a render of the
    held-out view 3, instead of reconstructing. mvs-only: the ground truth's first half;
    svolsdf: all of it, 0.4 world units up; volsdf: fails."""

    calls: list[tuple[str, str, int | None, list | None]] = []

    def __init__(self, cfg, out, progress=True):
        self.cfg, self.out = cfg, Path(out)

    def run(self):
        mode, scene = self.cfg.train.mode, Path(self.cfg.scene.path)
        FakePipeline.calls.append((scene.name, mode, self.cfg.train.steps,
                                   self.cfg.scene.image_size))
        if mode == "volsdf":
            raise RuntimeError("field diverged")
        self.out.mkdir(parents=True, exist_ok=True)
        gt = read_ply(scene / "gt_points.ply")["points"]
        pts = gt[: len(gt) // 2] if mode == "mvs-only" else gt + [0, 0, 0.4]
        write_points_ply(self.out / "points.ply", pts)
        (self.out / "views.json").write_text(json.dumps(
            {"inputs": [0, 1, 2], "test": [3], "size": [96, 72], "scene": str(scene)}))
        (self.out / "config.yaml").write_text(f"scene:\n  path: {scene}\n")
        (self.out / "timing.json").write_text(json.dumps(
            {"mvs1": {"seconds": 1.5}, "fusion": {"seconds": 0.5}, "total": {"seconds": 9}}))
        (self.out / "renders").mkdir(exist_ok=True)
        img = np.asarray(Image.open(scene / "image" / "000003.png"))
        noisy = np.clip(img.astype(int) + (8 if mode == "svolsdf" else 30), 0, 255)
        Image.fromarray(noisy.astype(np.uint8)).save(self.out / "renders" / "3.png")
        # An input-view render must not count: only views.json's held-out views are scored.
        Image.fromarray(np.zeros_like(img)).save(self.out / "renders" / "0.png")
        return {"points": str(self.out / "points.ply"), "mesh": None, "timing": {}}


def test_run_benchmark_with_stand_in_pipeline(tmp_path, monkeypatch, synth_scene):
    import svolsdf.commands.render
    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    FakePipeline.calls = []
    rendered = []

    def fake_render(out, views=None, ibr=False, size=None, progress=True):
        # the held-out views of runs with a field, by volume rendering and IBR
        rendered.append((Path(out).parent.name, Path(out).name, views, ibr, size))
        (Path(out) / "renders_ibr").mkdir(exist_ok=True)
        img = np.asarray(Image.open(Path(out) / "renders" / "3.png")).astype(int)
        Image.fromarray(np.clip(img + 4, 0, 255).astype(np.uint8)).save(
            Path(out) / "renders_ibr" / "3.png")
        return {}

    monkeypatch.setattr(svolsdf.commands.render, "render_outputs", fake_render)
    out = tmp_path / "bench"
    cfg = BenchmarkConfig(scenes=[synth_scene, synth_scene], modes=["svolsdf", "mvs-only",
                                                                     "volsdf"],
                          out=out, steps=7, size=(96, 72), lpips_net="alex",
                          lpips_weights=shared_path("weights", "lpips"), render_size=(48, 36))
    rows = run_benchmark(cfg)
    # volsdf failed before rendering; mvs-only has no field to render
    assert rendered == [(s, "svolsdf", [3], True, [48, 36]) for s in ("synth_a", "synth_a-2")]
    assert [(c[0], c[1]) for c in FakePipeline.calls] == [
        ("synth_a", m) for m in ("svolsdf", "mvs-only", "volsdf")] * 2
    assert all(c[2] == 7 and c[3] == [96, 72] for c in FakePipeline.calls)
    assert [(r["scene"], r["mode"]) for r in rows] == [
        (s, m) for s in ("synth_a", "synth_a-2") for m in ("svolsdf", "mvs-only", "volsdf")]
    for r in rows:
        if r["mode"] == "volsdf":
            assert r["status"].startswith("failed: RuntimeError: field diverged")
            assert r["overall"] is None
            continue
        # a synthetic scene is scored as `svolsdf evaluate` scores it: what the inputs observe
        assert r["status"] == "ok" and r["protocol"] == "synthetic"
        m = json.loads((out / r["scene"] / r["mode"] / "metrics.json").read_text())
        for k in ("accuracy", "completeness", "overall", "overall_dtu_rule"):
            assert r[k] == m["chamfer"][k]
        assert r["time_s"] == pytest.approx(2.0)  # stage seconds, not the "total" entry
        assert set(m["images"]["psnr"]["per_view"]) == {"3"}  # view 0 is an input
        assert (r["psnr_ibr"] is not None) == (r["mode"] == "svolsdf")
    sv = [r for r in rows if r["mode"] == "svolsdf"]
    mo = [r for r in rows if r["mode"] == "mvs-only"]
    assert sv[0]["accuracy"] > 0.1 and mo[0]["completeness"] > 1
    assert sv[0]["psnr"] > mo[0]["psnr"] > 10
    # The files: Markdown and CSV tables (2 scenes + mean), JSON rows.
    assert json.loads((out / "benchmark.json").read_text()) == rows
    table = list(csv.reader(io.StringIO((out / "benchmark.csv").read_text())))
    assert [t[0] for t in table] == ["scene", "synth_a", "synth_a-2", "mean"]
    hdr = table[0]
    assert "svolsdf_psnr" in hdr and "volsdf_overall" in hdr
    i = hdr.index("svolsdf_overall")
    assert float(table[3][i]) == pytest.approx(np.mean([r["overall"] for r in sv]))
    assert table[1][hdr.index("volsdf_overall")] == ""
    md = (out / "benchmark.md").read_text()
    assert "| synth_a |" in md and "| **mean** |" in md and "svolsdf PSNR" in md
    assert "synth_a / volsdf: failed: RuntimeError: field diverged" in md
    assert "protocol: synthetic" in md


def test_cli_benchmark_and_errors(tmp_path, monkeypatch, capsys, synth_scene):
    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    out = tmp_path / "b"
    main(["benchmark", "--scenes", str(synth_scene), "--modes", "mvs-only", "-o", str(out),
          "--steps", "3", "--size", "96x72", "--lpips-net", "alex"])
    text = capsys.readouterr().out
    assert "| synth_a |" in text and f"wrote {out / 'benchmark.md'}" in text
    assert (out / "benchmark.csv").is_file() and (out / "synth_a" / "mvs-only").is_dir()
    for argv, msg in (
        (["--scenes", str(synth_scene), "--modes", "nerf"], "unknown mode"),
        (["--scenes", str(tmp_path / "nope")], "scene folder does not exist"),
        (["--scenes", str(synth_scene), "--dtu-gt", str(tmp_path / "nodtu")],
         "DTU ground-truth folder does not exist"),
    ):
        with pytest.raises(SystemExit) as e:
            main(["benchmark", *argv, "-o", str(tmp_path / "x")])
        assert e.value.code == 2
        assert msg in capsys.readouterr().err


def test_dtu_scene_without_scan_number_is_refused(tmp_path, synth_scene):
    dtu = tmp_path / "dtu"
    dtu.mkdir()
    other = tmp_path / "plain"
    other.mkdir()
    with pytest.raises(InputError, match="no DTU scan number"):
        run_benchmark(BenchmarkConfig(scenes=[other], modes=["mvs-only"], out=tmp_path / "o",
                                      dtu_gt=dtu))


def test_real_mvs_only_run(tmp_path, synth_scene):
    """One real pipeline run (mvs-only, 3 views at 96x72) through the whole benchmark."""
    out = tmp_path / "real"
    rows = run_benchmark(BenchmarkConfig(scenes=[synth_scene], modes=["mvs-only"], out=out,
                                         views=[0, 1, 2], size=(96, 72), device="cpu"))
    (r,) = rows
    assert r["status"] == "ok", r["status"]
    run = out / "synth_a" / "mvs-only"
    assert (run / "points.ply").is_file() and (run / "metrics.json").is_file()
    assert json.loads((run / "views.json").read_text())["test"] == [3]
    # The row holds what `svolsdf evaluate` gives the run: the synthetic protocol (the ground
    # truth the input views observe), scored again here from the files
    from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run

    assert len(read_ply(run / "points.ply")["points"]) > 100
    again = evaluate_run(EvaluateConfig(out=run, scene=synth_scene, lpips_net="alex",
                                        report=False))
    assert r["protocol"] == again["chamfer"]["protocol"] == "synthetic"
    assert math.isfinite(r["overall"]) and r["overall"] > 0
    for k in ("accuracy", "completeness", "overall", "overall_dtu_rule"):
        assert r[k] == pytest.approx(again["chamfer"][k], rel=1e-9)
    assert r["time_s"] > 0 and r["psnr"] is None  # mvs-only renders no novel views
    assert "| synth_a |" in (out / "benchmark.md").read_text()


def test_bad_run_options_fail_before_any_run(tmp_path, monkeypatch):
    import svolsdf.pipeline as pl

    def never(*a, **k):
        raise AssertionError("a run started")

    monkeypatch.setattr(pl, "Pipeline", never)
    scene = tmp_path / "scene"
    scene.mkdir()
    cfg = BenchmarkConfig(scenes=[scene], modes=["mvs-only"], out=tmp_path / "b", steps=-5)
    with pytest.raises(InputError, match=r"--steps \(train.steps\) = -5"):
        run_benchmark(cfg)
    assert not (tmp_path / "b").exists()


def test_benchmark_plot_writes_a_chart(tmp_path):
    from svolsdf.commands.benchmark import benchmark_plot

    path = benchmark_plot(ROWS, tmp_path / "b.png", ["svolsdf", "mvs-only"])
    img = Image.open(path)
    assert img.size[0] > 300 and img.size[1] > 400  # two panels: Chamfer and PSNR
    assert not (tmp_path / "b.png.tmp.png").exists()
    with pytest.raises(InputError, match="no runs"):
        benchmark_plot([], tmp_path / "c.png")


def test_view_sets_and_rerun_skip_with_stand_in_pipeline(tmp_path, monkeypatch, capsys,
                                                         synth_scene):
    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    FakePipeline.calls = []
    out = tmp_path / "vs"
    argv = ["benchmark", "--scenes", str(synth_scene), "--modes", "mvs-only volsdf", "-o",
            str(out), "--views", "0 1 2; 0,1,3", "--lpips-net", "alex"]
    with pytest.raises(SystemExit) as e:  # the volsdf jobs fail
        main(argv)
    assert e.value.code == 1
    assert len(FakePipeline.calls) == 4
    md = (out / "benchmark.md").read_text()
    assert "| synth_a [0,1,2] |" in md and "| synth_a [0,1,3] |" in md
    assert (out / "synth_a" / "views-0-1-3" / "mvs-only" / "benchmark_row.json").is_file()
    assert (out / "benchmark.png").is_file()
    rows = json.loads((out / "benchmark.json").read_text())
    assert [r["views"] for r in rows] == [[0, 1, 2], [0, 1, 2], [0, 1, 3], [0, 1, 3]]
    # a rerun runs only the failed (volsdf) jobs again and writes the same table
    FakePipeline.calls = []
    with pytest.raises(SystemExit):
        main(argv)
    assert [c[1] for c in FakePipeline.calls] == ["volsdf", "volsdf"]
    assert (out / "benchmark.md").read_text() == md
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--scenes", str(synth_scene), "-o", str(out), "--address", "auto"])
    assert e.value.code == 2 and "only with --executor ray" in capsys.readouterr().err


def test_markdown_table_says_which_surface_the_mesh_columns_hold():
    """Mesh accuracy and completeness sit beside the points'; a column that mixes a Poisson
    mesh with a field mesh that replaced a failed one lists every run's kind."""
    a = {**_row("s1", "svolsdf", 1.0, 2.0), "mesh_accuracy": 1.1, "mesh_completeness": 1.9,
         "mesh_overall": 1.5, "mesh_source": "poisson"}
    b = {**_row("s2", "svolsdf", 1.0, 2.0), "mesh_accuracy": 3.0, "mesh_completeness": 2.0,
         "mesh_overall": 2.5, "mesh_source": "field (poisson failed: 12 fused points)"}
    md = benchmark_markdown([a, b])
    head = _cells(md.splitlines()[4])
    assert head[1:6] == ["svolsdf Acc.", "svolsdf Comp.", "svolsdf Chamfer", "svolsdf mesh Acc.",
                         "svolsdf mesh Comp."]
    assert "The mesh columns mix surfaces" in md
    assert "- s2 / svolsdf: field (poisson failed: 12 fused points)" in md
    same = benchmark_markdown([a, {**b, "mesh_source": "poisson"}])
    assert "mesh.ply of every run with a mesh column: poisson." in same
    assert "mix surfaces" not in same


def test_tables_say_how_the_mesh_columns_were_scored():
    """A row from `svolsdf evaluate` carries ``mesh_sampled`` ("surface"); a table says its mesh
    columns are surface-scored, and lists the rows whose meshes were scored by their vertices
    (metrics written before) rather than mix the two unsaid."""
    from svolsdf.commands.benchmark import run_metrics
    from svolsdf.evaluate.run_outputs import empty_metrics, mesh_chamfer_block

    metrics = empty_metrics()
    metrics["chamfer_mesh"] = mesh_chamfer_block(
        {"accuracy": 1.0, "completeness": 2.0, "overall": 1.5}, "synthetic", "mesh.ply", 0.2)
    row = run_metrics(metrics, "s1", "svolsdf", 10.0)
    assert row["mesh_overall"] == 1.5
    assert row["mesh_sampled"] == "surface" and row["mesh_density"] == 0.2
    assert run_metrics(empty_metrics(), "s1", "svolsdf", 10.0)["mesh_sampled"] is None
    a = {**_row("s1", "svolsdf", 1.0, 2.0), "mesh_overall": 1.5, "mesh_sampled": "surface"}
    b = {**_row("s2", "svolsdf", 1.0, 2.0), "mesh_overall": 2.5}  # an older metrics.json
    md = benchmark_markdown([a])
    assert "score mesh.ply by its surface" in md and "mix scorings" not in md
    md = benchmark_markdown([a, b])
    assert "The mesh columns mix scorings" in md and "- s2 / svolsdf" in md
    assert "- s1 / svolsdf" not in md
    assert "by its surface" not in benchmark_markdown([_row("s1", "svolsdf", 1.0, 2.0)])


def test_failed_jobs_make_the_benchmark_exit_non_zero_naming_them(tmp_path, monkeypatch,
                                                                   capsys, synth_scene):
    """A job that fails is a row with its status and the benchmark goes on, but the command
    does not end with status 0: the last line names each failed job."""
    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    out = tmp_path / "b"
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--scenes", str(synth_scene), "--modes", "mvs-only", "volsdf", "-o",
              str(out), "--size", "96x72", "--lpips-net", "alex", "--no-render"])
    res = capsys.readouterr()
    assert e.value.code == 1
    assert "| synth_a |" in res.out and (out / "benchmark.csv").is_file()  # tables written
    (last,) = res.err.strip().splitlines()[-1:]
    assert "1 of 2 job(s) failed" in last and "synth_a / volsdf" in last
    assert "field diverged" in last and "synth_a / mvs-only" not in last


@pytest.mark.parametrize("argv, msg", [
    (["--views", "0 1 9"], "--views 0 1 9: "),
    (["--views", "0 1 2; 0 1 7"], "view id 7 does not exist"),
    (["--views", "0 1 2; 2"], "expected a list of at least 2"),
    (["--scan", "65"], "--scan 65: only the DTU protocol uses it"),
    (["--dtu-gt", "DTU", "--scan", "65"], "ObsMask65_10.mat"),
])
def test_view_sets_and_scan_are_checked_before_any_job_starts(tmp_path, monkeypatch, capsys,
                                                              synth_scene, argv, msg):
    import svolsdf.pipeline

    def never(*a, **k):
        raise AssertionError("a job started")

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", never)
    (tmp_path / "DTU").mkdir()
    argv = [str(tmp_path / "DTU") if a == "DTU" else a for a in argv]
    out = tmp_path / "b"
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--scenes", str(synth_scene), "--modes", "mvs-only", "-o", str(out),
              *argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert msg in err
    assert not out.exists()


def test_no_ground_truth_warning_only_for_scenes_without_any(tmp_path, monkeypatch, caplog,
                                                             synth_scene):
    """A synthetic scene is scored against its own ground truth: no 'no ground-truth' warning
    for it; a scene without any still gets one."""
    import logging

    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    plain = tmp_path / "plain"
    plain.mkdir()
    for f in ("cameras.npz", "image"):
        src = synth_scene / f
        if src.is_dir():
            import shutil

            shutil.copytree(src, plain / f)
        else:
            (plain / f).write_bytes(src.read_bytes())
    with caplog.at_level(logging.WARNING, logger="svolsdf"):
        run_benchmark(BenchmarkConfig(scenes=[synth_scene, plain], modes=["mvs-only"],
                                      out=tmp_path / "b", lpips_net="alex", render=False))
    warned = [r.getMessage() for r in caplog.records if "no ground-truth geometry" in
              r.getMessage()]
    assert len(warned) == 1 and str(plain) in warned[0], warned
