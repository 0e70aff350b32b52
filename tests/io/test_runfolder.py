"""`RunFolder`, the one reader of a run folder: views.json, timing.json, metrics.json and the
outputs present, on folders as every version wrote them."""

from __future__ import annotations

import json
import logging

import pytest

from svolsdf.errors import InputError
from svolsdf.io.runfolder import RunFolder, RunViews, mesh_source


def test_views_as_reconstruct_writes_them_and_as_older_folders_did(tmp_path):
    run = RunFolder(tmp_path)
    assert run.views() is None and not run.is_run()  # no views.json
    run.views_file.write_text(json.dumps({"inputs": [2, 0, 1], "test": [3], "size": [96, 72],
                                          "scene": "/data/scene"}))
    assert run.views() == RunViews([2, 0, 1], [3], (96, 72), "/data/scene")
    run.views_file.write_text(json.dumps({"inputs": [0, 2, 3], "test": [1]}))  # no size, scene
    assert run.views() == RunViews([0, 2, 3], [1], None, None)
    run.config_file.write_text("scene:\n  path: x\n")
    assert run.is_run()


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"inputs": ["a"]}',
                                  '{"inputs": [0], "size": [96]}'])
def test_unreadable_views_are_none_with_a_warning(tmp_path, caplog, text):
    run = RunFolder(tmp_path)
    run.views_file.write_text(text)
    with caplog.at_level(logging.WARNING):
        assert run.views() is None
    assert "views.json is unreadable" in caplog.text


def test_timing_missing_unreadable_and_mesh_source(tmp_path):
    run = RunFolder(tmp_path)
    assert run.timing() == {} and run.mesh_source() is None
    run.timing_file.write_text("{not json")
    assert run.timing() is None
    run.timing_file.write_text(json.dumps({"mesh": {"method": "poisson",
                                                    "poisson_failed": "no points"}}))
    assert run.mesh_source() == "field (poisson failed: no points)"  # before mesh_source
    assert mesh_source({"mesh": {"mesh_source": "tsdf"}}) == "tsdf"
    assert mesh_source({"mesh": {"seconds": 1.0}}) == "field"


def test_metrics_missing_and_invalid(tmp_path):
    run = RunFolder(tmp_path)
    assert run.metrics() is None
    run.metrics_file.write_text('{"fscore": 0.5}')
    assert run.metrics() == {"fscore": 0.5}
    run.metrics_file.write_text("[0.5]")
    with pytest.raises(InputError, match="metrics.json: not valid JSON"):
        run.metrics()


def test_outputs_and_render_files(tmp_path):
    run = RunFolder(tmp_path)
    assert run.outputs() == [] and run.render_files() == {}
    run.points.write_bytes(b"ply")
    for name in ("10.png", "2.png", "orbit.png", "3.txt"):
        run.renders_dir().mkdir(exist_ok=True)
        (run.renders_dir() / name).write_bytes(b"")
    run.renders_dir(ibr=True).mkdir()  # empty: no output
    assert run.outputs() == ["points.ply", "renders"]
    assert list(run.render_files()) == [2, 10]
    assert list(run.render_files(views=[10, 7])) == [10]
    assert run.render_files(ibr=True) == {}
