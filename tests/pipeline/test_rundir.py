"""`RunDir` (stage state, atomic saves, timing), `stage_keys` without a scene, `Run.open`'s
errors, what `Pipeline` refuses before any stage, the regressed stage-1 depth the field stage
takes, and the components that moved out of the pipeline (issue 33)."""

from __future__ import annotations

import copy
import json
import logging

import numpy as np
import pytest
import torch
from tiny_pipeline import make_tiny_scene, tiny_cfg

from svolsdf.config import load_config, preset
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


def test_unreadable_file_errors_are_those_of_damaged_files_not_of_bugs(tmp_path):
    """Issue 50: what numpy and torch raise for a truncated or corrupt .npy, .npz and torch
    file, and a key an older file lacks, counts as an unreadable file; a loader's bug does not."""
    from svolsdf.pipeline.rundir import is_unreadable_file

    np.save(tmp_path / "a.npy", np.zeros((40, 50), np.float32))
    np.savez(tmp_path / "a.npz", x=np.arange(4000.0), y=np.zeros(3))
    torch.save({"model_state_dict": {"w": torch.zeros(500)}}, tmp_path / "a.pt")
    loaders = {".npy": np.load, ".npz": lambda p: dict(np.load(p)),
               ".pt": lambda p: torch.load(p, weights_only=False)["model_state_dict"]}
    seen = set()
    for suffix, load in loaders.items():
        data = (tmp_path / f"a{suffix}").read_bytes()
        for n in (0, 1, 10, len(data) // 2, len(data) - 1):
            (tmp_path / f"cut{suffix}").write_bytes(data[:n])
            with pytest.raises(Exception) as e:
                load(tmp_path / f"cut{suffix}")
            assert is_unreadable_file(e.value), (suffix, n, repr(e.value))
            seen.add(type(e.value).__name__)
    torch.save({"older": 1}, tmp_path / "old.pt")  # a layout without the key
    with pytest.raises(KeyError) as e:
        loaders[".pt"](tmp_path / "old.pt")
    assert is_unreadable_file(e.value)
    assert len(seen) >= 3, seen  # ValueError, EOFError, BadZipFile, RuntimeError, ...
    for bug in (TypeError("x"), AttributeError("x"), NameError("x"), NotImplementedError("x"),
                RecursionError("x"), AssertionError("x")):
        assert not is_unreadable_file(bug), bug


def test_timing_merges_and_atomic_saves(tmp_path):
    rd = RunDir(tmp_path)
    rd.write_timing({"mvs1": {"seconds": 1.0}})
    rd.write_timing({"field": {"seconds": 2.0}})
    assert set(json.loads(rd.timing_file.read_text())) == {"mvs1", "field"}
    rd.save_npy(tmp_path / "a" / "x.npy", np.arange(3, dtype=np.float32))
    assert np.load(tmp_path / "a" / "x.npy").tolist() == [0, 1, 2]
    # the mesh file follows mesh.format, in the run folder; the refined field's depth
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
    with pytest.raises(InputError, match="run folder does not exist"):
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


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_tiny_scene(tmp_path_factory.mktemp("syn") / "scene")


def test_bad_inputs_name_the_problem(tiny_scene, tmp_path):
    cfg = tiny_cfg(tiny_scene)
    cfg.scene.views = [0, 1, 99]
    with pytest.raises(InputError, match="99"):
        Pipeline(cfg, tmp_path / "a", progress=False).run()
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        Pipeline(tiny_cfg(tiny_scene), f, progress=False)
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  stepz: 3\n")
    with pytest.raises(InputError, match="stepz"):
        load_config(bad)
    cfg = tiny_cfg(tiny_scene)
    cfg.mvs.finer_stage_optimization = True
    cfg.train.mode = "volsdf"
    with pytest.raises(InputError, match="finer_stage_optimization"):
        Pipeline(cfg, tmp_path / "b", progress=False).run()


def test_an_unrecognised_scene_folder_leaves_no_run_folder(tmp_path):
    """Issue 38: a folder no scene format reads is refused before OUT (and OUT/log) exists."""
    scene = tmp_path / "not_a_scene"
    scene.mkdir()
    (scene / "notes.txt").write_text("no cameras here")
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    out = tmp_path / "out"
    with pytest.raises(InputError, match="no known scene layout"):
        Pipeline(cfg, out, progress=False).run()
    assert not (out / "log").exists() and not out.exists()


def test_field_stage_uses_the_regressed_stage1_depth(tmp_path):
    # the plane sweep stores the main-mode depth; the field stage takes sum_k P_k d_k (2.4)
    from svolsdf.mvs.volume import ProbabilityVolume
    from svolsdf.scene.cameras import Cameras

    cam = Cameras(K=torch.tensor([[[4.0, 0, 2], [0, 4.0, 1.5], [0, 0, 1]]]),
                  w2c=torch.eye(4)[None], width=4, height=3)
    depths = torch.linspace(1, 2, 5).view(5, 1, 1).expand(5, 3, 4).contiguous()
    prob = torch.zeros(5, 3, 4)
    prob[0], prob[4] = 0.6, 0.4  # bimodal: mode depth 1.0, expectation 1.4
    vol = ProbabilityVolume(depths, prob, torch.ones(3, 4), torch.ones(3, 4), cam, 0)
    cfg = preset("fast")
    cfg.scene.path = str(tmp_path)
    p = Pipeline(cfg, tmp_path / "o")
    assert p.regressed_volumes1() is None
    p.volumes1 = [vol]
    reg = p.regressed_volumes1()
    torch.testing.assert_close(reg[0].depth, torch.full((3, 4), 1.4))
    assert vol.depth.eq(1).all()  # the stored volume is left as it is
    assert p.regressed_volumes1() is reg  # cached
