"""`RunDir` (stage state, atomic saves, timing), `stage_keys` without a scene, `Run.open`'s
errors, and the components that moved out of the pipeline (issue 33)."""

from __future__ import annotations

import copy
import json
import logging

import numpy as np
import pytest
import torch

from svolsdf.config import preset
from svolsdf.errors import InputError
from svolsdf.pipeline import STAGES, Pipeline, Run, RunDir, stage_keys


def test_stage_state_round_trip(tmp_path):
    rd = RunDir(tmp_path)
    assert rd.state() == {} and not rd.done("mvs1", "k")
    for s in STAGES:
        rd.mark(s, f"k{s}")
    assert rd.done("field", "kfield") and not rd.done("field", "other")
    rd.unmark(STAGES[STAGES.index("guide"):])  # a stage and the later ones
    assert set(rd.state()) == {"mvs1", "field"}
    assert not any(p.suffix == ".tmp" for p in tmp_path.iterdir())  # written atomically


def test_unreadable_state_counts_as_nothing_finished(tmp_path, caplog):
    rd = RunDir(tmp_path)
    rd.stages_file.write_text("{not json")
    with caplog.at_level(logging.WARNING):
        assert rd.state() == {} and rd.state() == {}
    assert sum("unreadable" in r.message for r in caplog.records) == 1  # warned once
    rd.mark("mvs1", "k")  # replaces it
    assert rd.state() == {"mvs1": "k"}


def test_timing_merges_and_atomic_saves(tmp_path):
    rd = RunDir(tmp_path)
    rd.write_timing({"mvs1": {"seconds": 1.0}})
    rd.write_timing({"field": {"seconds": 2.0}})
    assert set(json.loads(rd.timing_file.read_text())) == {"mvs1", "field"}
    rd.save_npy(tmp_path / "a" / "x.npy", np.arange(3, dtype=np.float32))
    assert np.load(tmp_path / "a" / "x.npy").tolist() == [0, 1, 2]
    # the mesh file follows output.mesh_format, in the run folder; the refined field's depth
    # (finer-stage optimization) does not overwrite the guide's
    assert rd.mesh("obj").suffix == ".obj" and rd.mesh().suffix == ".ply"
    assert rd.mesh("obj").parent == rd.mesh().parent == rd.root
    assert rd.render_depth_dir(refined=True) != rd.render_depth_dir()


def test_stage_keys_need_no_scene_and_match_the_pipeline(tmp_path):
    cfg = preset("fast")
    cfg.scene.path = str(tmp_path)
    keys = stage_keys(cfg, [0, 1, 2])
    assert set(keys) == set(STAGES)
    assert keys == stage_keys(copy.deepcopy(cfg), [0, 1, 2])
    assert stage_keys(cfg, [0, 1, 3])["mvs1"] != keys["mvs1"]  # the views enter every key
    p = Pipeline(cfg, tmp_path / "o")
    p.views = [0, 1, 2]
    p.load = lambda: None  # the keys read no scene
    assert p.stage_keys() == keys


def test_run_open_needs_a_run_folder(tmp_path):
    with pytest.raises(InputError, match="no such run folder"):
        Run.open(tmp_path / "missing")
    with pytest.raises(InputError, match="not a run folder"):
        Run.open(tmp_path)


def test_guide_depth_rule():
    from svolsdf.render.views import guide_depths

    depth = torch.tensor([[[1.0, 2.0], [3.0, 4.0]]])
    opacity = torch.tensor([[[1.0, 1.0], [0.1, 1.0]]])
    out = guide_depths(depth, opacity, [7], 2.0, "max")  # docs/method.md 6.1: the map's maximum
    assert out[7].tolist() == [[2.0, 4.0], [8.0, 8.0]]
    kept = guide_depths(depth, opacity, [7], 2.0, "none")
    assert kept[7].tolist() == [[2.0, 4.0], [6.0, 8.0]]
