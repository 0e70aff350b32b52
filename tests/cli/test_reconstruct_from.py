"""``svolsdf reconstruct -o OUT --from STAGE``: fusion and meshing run again alone on a finished
run folder after a fusion or mesh option changed; a stage before STAGE that would have to run
again, an unknown stage or a folder that is no run is refused (exit 2) before anything is
written."""

from __future__ import annotations

import json
import logging

import pytest
from tests.pipeline.tiny_pipeline import (
    cli,
    cli_exit,
    copy_run,
    make_small_sphere_scene,
    small_field_run,
)


@pytest.fixture(scope="module")
def field_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("from")
    return small_field_run(make_small_sphere_scene(folder / "scene"), folder)


def _times(run) -> dict:
    return json.loads((run / "timing.json").read_text())


def test_from_fusion_reruns_fusion_and_mesh_alone(field_run, tmp_path, caplog):
    run = copy_run(field_run, tmp_path / "run")
    before = _times(run)
    caplog.set_level(logging.INFO)
    upstream = {k: before[k] for k in ("mvs1", "field", "guide", "mvs23")}
    mesh = (run / "mesh.ply").read_bytes()
    cli(["reconstruct", "-o", run, "--from", "fusion", "--set", "mesh.method=tsdf",
         "--no-progress"])
    after = _times(run)
    assert {k: after[k] for k in upstream} == upstream  # read back, not run
    # fusion ran again (its timing record may repeat to the millisecond on a tiny scene)
    assert any(r.message.startswith("fused ") for r in caplog.records), caplog.text
    assert after["mesh"]["method"] == "tsdf"
    assert (run / "mesh.ply").read_bytes() != mesh
    assert "method: tsdf" in (run / "config.yaml").read_text()


def test_from_refuses_a_stage_before_it_that_would_run_again(field_run, tmp_path, capsys):
    run = copy_run(field_run, tmp_path / "run")
    state = (run / "stages.json").read_bytes()
    code, res = cli_exit(["reconstruct", "-o", run, "--from", "fusion", "--set",
                          "train.steps=11", "--no-progress"], capsys)
    assert code == 2 and "stage field" in res.err and "without --from" in res.err, res.err
    assert (run / "stages.json").read_bytes() == state


@pytest.mark.parametrize("argv, says", [(["--from", "polish"], "unknown stage"),
                                        (["--from", "mesh"], "not a run folder")])
def test_from_refuses_an_unknown_stage_or_a_folder_without_a_run(tmp_path, capsys, argv, says):
    code, res = cli_exit(["reconstruct", "-o", tmp_path / "none", *argv], capsys)
    assert code == 2 and says in res.err, res.err
    assert not (tmp_path / "none").exists()
