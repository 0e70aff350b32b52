"""``svolsdf benchmark --experiment FILE`` and ``--preset/--set/--config`` for one variant: the
jobs, the resume, the record and what it renders, and the refusals before any work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from tests.commands.test_benchmark import FakePipeline

from svolsdf.cli import main
from svolsdf.commands.experiment import (
    PRESET_TUNED_ON,
    experiment_markdown,
    load_experiment,
    public_command,
)
from svolsdf.errors import InputError


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A data folder holding one small synthetic scene, ``synth_a``."""
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    root = tmp_path_factory.mktemp("data")
    make_synthetic_scene(root / "synth_a", SynthConfig(views=4, width=96, height=72,
                                                       gt_points=4000, supersample=1,
                                                       mesh_resolution=6.0))
    return root


EXPERIMENT = """\
name: tiny-ablation
description: Two variants of the fast preset and a baseline that fails.
scenes: [synth_a]
views: [[0, 1, 2]]
size: 96x72
steps: 5
variants:
  full: {preset: fast}
  ce: {preset: fast, set: [train.ablation=ce], tuned_on: synth_a only}
  baseline: {preset: fast, set: [train.mode=volsdf]}
"""


def _fake(monkeypatch):
    import svolsdf.pipeline

    monkeypatch.setattr(svolsdf.pipeline, "Pipeline", FakePipeline)
    FakePipeline.calls = []
    seen = []
    orig = FakePipeline.__init__

    def init(self, cfg, out, progress=True):
        seen.append((Path(out).name, cfg.train.mode, cfg.train.ablation, cfg.train.steps,
                     cfg.preset))
        orig(self, cfg, out, progress)

    monkeypatch.setattr(FakePipeline, "__init__", init)
    return seen


def test_experiment_runs_variants_records_and_resumes(tmp_path, monkeypatch, capsys, data):
    seen = _fake(monkeypatch)
    exp = tmp_path / "tiny.yaml"
    exp.write_text(EXPERIMENT)
    out = tmp_path / "out"
    argv = ["benchmark", "--experiment", str(exp), "--data", str(data), "-o", str(out),
            "--lpips-net", "alex", "--no-render"]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 1  # the failed baseline makes the command fail
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "1 of 3 job(s) failed" in err and "synth_a / baseline" in err
    assert seen == [("full", "svolsdf", None, 5, "fast"), ("ce", "svolsdf", "ce", 5, "fast"),
                    ("baseline", "volsdf", None, 5, "fast")]
    rec = json.loads((out / "experiment.json").read_text())
    assert [r["mode"] for r in rec["rows"]] == ["full", "ce", "baseline"]
    assert [r["run_mode"] for r in rec["rows"]] == ["svolsdf", "svolsdf", "volsdf"]
    assert rec["rows"][2]["status"].startswith("failed: RuntimeError: field diverged")
    assert rec["rows"][0]["overall"] is not None
    assert rec["experiment"] == "tiny-ablation" and rec["file"] == "tiny.yaml"
    assert rec["commit"] and rec["machine"]["cores"] and rec["view_sets"] == [[0, 1, 2]]
    assert "--experiment DATA/tiny.yaml" in rec["command"] and str(tmp_path) not in rec["command"]
    tuned = {v["name"]: v["tuned_on"] for v in rec["variants"]}
    assert tuned == {"full": PRESET_TUNED_ON["fast"], "ce": "synth_a only",
                     "baseline": PRESET_TUNED_ON["fast"]}
    md = (out / "experiment.md").read_text()
    assert md == experiment_markdown(rec)  # rendered from the record
    assert "| synth_a |" in md and "full Chamfer" in md and "ce Chamfer" in md
    assert "synth_a / baseline: failed" in md and "`train.ablation=ce`" in md
    assert (out / "experiment.png").stat().st_size > 1000
    assert (out / "synth_a" / "ce" / "benchmark_row.json").is_file()
    # a rerun runs only the failed job again
    seen.clear()
    with pytest.raises(SystemExit):
        main(argv)
    assert [s[0] for s in seen] == ["baseline"]


def test_command_line_preset_set_and_config_make_one_variant(tmp_path, monkeypatch, data):
    seen = _fake(monkeypatch)
    out = tmp_path / "out"
    main(["benchmark", "--scenes", str(data / "synth_a"), "--modes", "svolsdf", "-o", str(out),
          "--size", "96x72", "--lpips-net", "alex", "--no-render", "--preset", "draft",
          "--set", "train.ablation=mse", "--set", "train.steps=4"])
    assert seen == [("svolsdf", "svolsdf", "mse", 4, "draft")]
    assert "preset draft, --set train.ablation=mse train.steps=4" in \
        (out / "benchmark.md").read_text()
    from svolsdf.config import preset, save_config

    c = preset("fast")
    c.train.ablation = "no-prob-volume"
    save_config(c, tmp_path / "c.yaml")
    seen.clear()
    main(["benchmark", "--scenes", str(data / "synth_a"), "--modes", "svolsdf", "-o",
          str(tmp_path / "out2"), "--size", "96x72", "--lpips-net", "alex", "--no-render",
          "--config", str(tmp_path / "c.yaml")])
    assert seen[0][2] == "no-prob-volume"


@pytest.mark.parametrize("text, msg", [
    ("scenes: [synth_a]\n", "variants: expected a mapping"),
    ("scenes: synth_a\nvariants: {a: {}}\n", "scenes: expected a list"),
    ("scenes: [nope]\nvariants: {a: {}}\n", "scenes: nope is no folder"),
    ("scenes: [synth_a]\nvariants: {a: {preset: slow}}\n", "variants.a.preset: unknown preset"),
    ("scenes: [synth_a]\nvariants: {a: {set: [train.ablation=gce]}}\n",
     "variants.a: set train.ablation"),
    ("scenes: [synth_a]\nvariants: {a: {set: [train.nothing=1]}}\n", "variants.a:"),
    ("scenes: [synth_a]\nvariants: {a: {sets: []}}\n", "variants.a.sets: unknown key"),
    ("scenes: [synth_a]\nviews: [[0, 0]]\nvariants: {a: {}}\n", "views: expected"),
    ("scenes: [synth_a]\nsize: big\nvariants: {a: {}}\n", "size:"),
    ("scenes: [synth_a]\nvariant: {a: {}}\n", "variant: unknown key"),
    ("scenes: [synth_a]\nplot: {kind: sweep, x: train.gce_q}\nvariants: {a: {}}\n",
     "plot.x: variant a sets no number for train.gce_q"),
    ("scenes: [synth_a\n", "not a readable YAML file"),
    ("scenes: [synth_a]\nscene_views: {other: [0, 1]}\nvariants: {a: {}}\n",
     "scene_views.other: not one of the file's scenes"),
    ("scenes: [synth_a]\nscene_views: {synth_a: [0]}\nvariants: {a: {}}\n",
     "scene_views.synth_a: expected a list of at least two"),
])
def test_bad_experiment_files_are_refused_before_any_work(tmp_path, monkeypatch, capsys, data,
                                                          text, msg):
    seen = _fake(monkeypatch)
    exp = tmp_path / "bad.yaml"
    exp.write_text(text)
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--experiment", str(exp), "--data", str(data), "-o", str(out)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(exp) in err[0] and msg in err[0], err
    assert not seen and not out.exists()


def test_scene_views_give_a_scene_its_own_inputs(tmp_path, monkeypatch, capsys, data):
    # BlendedMVS' scans each have their own three input views: scene_views, in place of views
    _fake(monkeypatch)
    exp = tmp_path / "own.yaml"
    exp.write_text("scenes: [synth_a]\nviews: [[0, 1, 2]]\nscene_views: {synth_a: [3, 1, 2]}\n"
                   "size: 96x72\nsteps: 5\nvariants: {full: {preset: fast}}\n")
    out = tmp_path / "out"
    main(["benchmark", "--experiment", str(exp), "--data", str(data), "-o", str(out),
          "--lpips-net", "alex", "--no-render"])
    rec = json.loads((out / "experiment.json").read_text())
    assert [r["views"] for r in rec["rows"]] == [[3, 1, 2]]
    assert rec["scene_views"] == {"synth_a": [3, 1, 2]}
    assert "synth_a: input views [3, 1, 2]" in (out / "experiment.md").read_text()
    # a view the scene does not have: refused before any job, naming where it came from
    exp.write_text("scenes: [synth_a]\nscene_views: {synth_a: [0, 9, 1]}\n"
                   "variants: {full: {preset: fast}}\n")
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--experiment", str(exp), "--data", str(data), "-o",
              str(tmp_path / "out2")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "scene_views 0 9 1" in err and "9" in err
    assert not (tmp_path / "out2").exists()


def test_experiment_contradicting_options_are_refused(tmp_path, capsys, data):
    exp = tmp_path / "e.yaml"
    exp.write_text(EXPERIMENT)
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--experiment", str(exp), "--data", str(data), "--set",
              "train.steps=3", "-o", str(tmp_path / "o")])
    assert e.value.code == 2 and "--set would contradict" in capsys.readouterr().err
    with pytest.raises(InputError, match="no such file"):
        load_experiment(tmp_path / "missing.yaml")


def test_public_command_names_no_machine_path():
    assert public_command(["svolsdf", "benchmark", "--data", "/a/b/data", "x=/c/d"]) == \
        "svolsdf benchmark --data DATA/data x=DATA/d"


def test_record_renders_the_field_alone_table():
    """A record with ``field_alone`` (benchmarks/experiment_results.py --field-alone) renders
    it as a second table, one column per variant, from the record alone."""
    rec = {"experiment": "x", "description": None, "paper": None, "file": "x.yaml",
           "command": "svolsdf benchmark", "commit": "abc1234", "version": "0",
           "machine": {"cpu": "cpu", "cores": 2, "torch": "2"}, "date": "2026-12-07",
           "scenes": ["s"], "view_sets": [[0, 1, 2]], "size": [96, 72], "steps": 5,
           "variants": [{"name": n, "preset": "fast", "set": [], "config": None,
                         "mode": "svolsdf", "tuned_on": "t"} for n in ("full", "mse")],
           "plot": {"kind": "bars", "metric": "overall"},
           "rows": [{"scene": "s", "mode": n, "status": "ok", "accuracy": 1.0,
                     "completeness": 2.0, "overall": 1.5, "time_s": 3.0} for n in ("full", "mse")],
           "field_alone": {"what": "Guide depth.", "rows": [
               {"scene": "s", "variant": "full", "median_mm": 1.58, "within_2mm": 0.55},
               {"scene": "s", "variant": "mse", "median_mm": 1.84, "within_2mm": 0.52}]}}
    md = experiment_markdown(rec)
    assert "## The field alone" in md and "| s | 1.58 (55 %) | 1.84 (52 %) |" in md


def test_record_renders_the_pseudo_ground_truth_table():
    """A record with ``pseudo_gt`` (benchmarks/experiment_results.py --pseudo-gt: DTU scans
    scored against their many-view reference) renders one row per scene and variant, a
    missing mesh as '-'."""
    rec = {"experiment": "x", "description": None, "paper": None, "file": "x.yaml",
           "command": "svolsdf benchmark", "commit": "abc1234", "version": "0",
           "machine": {"cpu": "cpu", "cores": 2, "torch": "2"}, "date": "2026-12-07",
           "scenes": ["dtu_scan65"], "view_sets": [[25, 22, 28]], "size": [768, 576],
           "steps": None,
           "variants": [{"name": n, "preset": "fast", "set": [], "config": None,
                         "mode": "svolsdf", "tuned_on": "t"} for n in ("full", "mse")],
           "plot": {"kind": "bars", "metric": "overall"},
           "rows": [{"scene": "dtu_scan65", "mode": n, "status": "ok", "accuracy": None,
                     "completeness": None, "overall": None, "time_s": 3.0}
                    for n in ("full", "mse")],
           "pseudo_gt": {"what": "Against the reference.", "rows": [
               {"scene": "dtu_scan65", "variant": "full", "points_accuracy": 2.0,
                "points_completeness": 1.82, "points_overall": 1.91,
                "points_overall_dtu_rule": 1.75, "points_fscore": 0.789,
                "mesh_overall": 2.14, "mesh_overall_dtu_rule": 2.04},
               {"scene": "dtu_scan65", "variant": "mse", "points_accuracy": 2.1,
                "points_completeness": 1.9, "points_overall": 2.0,
                "points_overall_dtu_rule": 1.8, "points_fscore": 0.7}]}}
    md = experiment_markdown(rec)
    assert "## Against the pseudo ground truth" in md
    assert "| dtu_scan65 | full | 2.00 | 1.82 | 1.91 | 1.75 | 0.79 | 2.14 | 2.04 |" in md
    assert "| dtu_scan65 | mse | 2.10 | 1.90 | 2.00 | 1.80 | 0.70 | - | - |" in md


def test_plot_of_a_record_without_chamfer_shows_the_pseudo_ground_truth(monkeypatch, tmp_path):
    """DTU scans without their STL have no Chamfer in the rows: the bars show the one against
    the pseudo ground truth (``pseudo_gt``), not empty bars."""
    import svolsdf.commands.experiment as exp

    seen = {}
    monkeypatch.setattr(exp, "benchmark_plot",
                        lambda rows, path, names: seen.setdefault("rows", rows))
    rec = {"variants": [{"name": "full"}], "plot": {"kind": "bars"},
           "rows": [{"scene": "dtu_scan65", "mode": "full", "status": "ok", "overall": None}],
           "pseudo_gt": {"rows": [{"scene": "dtu_scan65", "variant": "full",
                                   "points_accuracy": 2.0, "points_completeness": 1.82,
                                   "points_overall": 1.91}]}}
    exp.experiment_plot(rec, tmp_path / "x.png")
    assert seen["rows"][0]["overall"] == 1.91 and seen["rows"][0]["accuracy"] == 2.0
