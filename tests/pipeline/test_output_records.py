"""The record of each finished stage's files (size and BLAKE2b digest in OUT/stages.json): a
file cut short or replaced after its stage finished reruns the stage and is never scored or
rendered from; run folders without the record keep their stages (docs/run-folder.md "Finished
outputs are checked")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from tests.pipeline.tiny_pipeline import cli as _main
from tests.pipeline.tiny_pipeline import cli_exit as _run
from tests.pipeline.tiny_pipeline import copy_run as _copy
from tests.pipeline.tiny_pipeline import make_small_sphere_scene, small_field_run

from svolsdf.pipeline import STAGES


@pytest.fixture(scope="module")
def field_run(tmp_path_factory):
    """A finished run with a field of a 64x48 sphere (a 16^3 grid, 10 steps: seconds)."""
    d = tmp_path_factory.mktemp("records")
    return small_field_run(make_small_sphere_scene(d / "scene"), d)


def _truncate(path: Path) -> None:
    """Cut a file to half its bytes, as a full disk or a killed copy leaves it."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("stage, rel", [("fusion", "points.ply"), ("mesh", "mesh.ply"),
                                        ("mvs23", "depth/1.npy"), ("field", "field/model.pt")])
def test_a_finished_output_cut_short_or_replaced_reruns_its_stage(field_run, tmp_path, stage,
                                                                  rel):
    """A truncated points.ply or mesh.ply was reused as finished: each stage's marker records
    the size and digest of its files, and a file that differs on a rerun reruns the stage (and
    the later ones), with the reason in OUT/log and timing.json."""
    out = _copy(field_run, tmp_path / "run")
    original = (out / rel).read_bytes()
    st = json.loads((out / "stages.json").read_text())
    assert st["outputs"][stage][rel]["size"] == len(original)
    _truncate(out / rel)
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    timing = json.loads((out / "timing.json").read_text())
    why = f"{out / rel} has {len(original) // 2} bytes, {len(original)} when the stage finished"
    assert timing[stage]["rerun"] == why
    assert f"{why}; running the stage {stage} again" in (out / "log").read_text()
    assert set(STAGES[STAGES.index(stage):]) - {"unguided"} <= set(timing)
    assert len((out / rel).read_bytes()) == len(original)
    if stage not in ("fusion", "mesh"):
        return
    # the same size, other bytes: found by the digest
    flipped = bytearray((out / rel).read_bytes())
    flipped[-1] ^= 1
    (out / rel).write_bytes(bytes(flipped))
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    timing = json.loads((out / "timing.json").read_text())
    assert timing[stage]["rerun"] == f"{out / rel} changed since the stage finished (another " \
                                      "blake2b digest)"


def test_evaluate_and_render_refuse_an_output_changed_since_its_stage(field_run, tmp_path,
                                                                     capsys):
    """A points.ply, mesh.ply or model.pt cut short after the run finished is not scored or
    rendered from: one line names the file and the command that makes it again."""
    for rel, argv in (("points.ply", ["evaluate"]), ("mesh.ply", ["report"]),
                      ("field/model.pt", ["render"])):
        out = _copy(field_run, tmp_path / rel.replace("/", "_"))
        f = out / rel
        data = f.read_bytes()
        f.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # the same size, another content
        code, res = _run(argv + [out], capsys)
        assert code == 2, res.err
        assert f"{f} changed since the stage finished" in res.err
        assert f"svolsdf reconstruct -o {out}" in res.err and len(res.err.splitlines()) == 1


def test_a_run_folder_without_output_records_is_reused(field_run, tmp_path):
    """Folders from before the record keep every finished stage (only what was recorded is
    checked)."""
    out = _copy(field_run, tmp_path / "run")
    st = json.loads((out / "stages.json").read_text())
    del st["outputs"]  # as run folders were written before the record
    (out / "stages.json").write_text(json.dumps(st))
    before = json.loads((out / "timing.json").read_text())
    _main(["reconstruct", "-o", out, "--config", out / "config.yaml", "--no-progress"])
    assert json.loads((out / "timing.json").read_text()) == {**before, "total": json.loads(
        (out / "timing.json").read_text())["total"]}  # no stage ran
    assert "outputs" not in json.loads((out / "stages.json").read_text())
