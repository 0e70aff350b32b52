"""A run folder made before the stages were declared objects (tests/pipeline/data/run_0c42d68:
`svolsdf reconstruct` at commit 0c42d68 of the small synthetic sphere, views 0 1 2 at 32x24, a
short fast-preset field with the field's own mesh, the scene given as the relative path
``scene`` so that its stage keys do not depend on where the test runs) is recognised: rerun, it
computes nothing; with its last stages forgotten (a run killed after the depth), it computes
those alone and writes the same bytes.

The fixture was made when ``mvs.width = paper`` meant (1, 1, 0.5); it now means the paper's
explicit (1, 0.5, 0.5), and the old reading is named ``half-default`` (docs/method.md 2.5). The
copy the tests rerun says ``half-default``, the option its stages ran with; the fixture as made
(``paper``) keeps the stages before the finer MVS stages and runs those again."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest
from tiny_pipeline import cli, make_small_sphere_scene

FIXTURE = Path(__file__).parent / "data" / "run_0c42d68"
# config.yaml is written again with every option of today's schema (options added since the
# fixture appear with their defaults); run.json records the command that last finished
_BOOKKEEPING = {"log", "timing.json", "stages.json", ".svolsdf.lock", "config.yaml", "run.json"}


@pytest.fixture
def old_run(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    make_small_sphere_scene(Path("scene"))
    run = Path(shutil.copytree(FIXTURE, tmp_path / "run"))
    cfg = run / "config.yaml"
    text = cfg.read_text()
    assert "  width: paper\n" in text
    cfg.write_text(text.replace("  width: paper\n", "  width: half-default\n"))
    return run


@pytest.fixture
def old_run_as_made(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    make_small_sphere_scene(Path("scene"))
    return Path(shutil.copytree(FIXTURE, tmp_path / "run"))


def _files(run: Path) -> dict[str, bytes]:
    return {f.relative_to(run).as_posix(): f.read_bytes() for f in sorted(run.rglob("*"))
            if f.is_file() and f.relative_to(run).as_posix() not in _BOOKKEEPING}


def _stage_times(run: Path) -> dict:
    return {k: v for k, v in json.loads((run / "timing.json").read_text()).items()
            if k != "total"}


def _rewritten(run: Path, stage: str, since_ns: int) -> bool:
    """Every output file stages.json records for ``stage`` was written after ``since_ns`` (a
    stage's timing record can repeat to the millisecond on a tiny scene; its files' times do
    not)."""
    names = json.loads((run / "stages.json").read_text())["outputs"][stage]
    return all((run / n).stat().st_mtime_ns > since_ns for n in names)


def _current_keys(run: Path) -> dict[str, str]:
    from svolsdf.config import load_config
    from svolsdf.pipeline.keys import stage_keys

    views = json.loads((run / "views.json").read_text())["inputs"]
    return stage_keys(load_config(run / "config.yaml"), views)


def _rerun() -> None:
    cli(["reconstruct", "-o", "run", "--config", "run/config.yaml", "--no-progress"])


def test_an_old_run_folder_is_reused_without_computing_anything(old_run):
    files, times = _files(old_run), _stage_times(old_run)
    markers = {k: v for k, v in json.loads((old_run / "stages.json").read_text()).items()
               if isinstance(v, str)}
    _rerun()
    assert _files(old_run) == files
    assert _stage_times(old_run) == times  # no stage ran (each would have timed itself)
    state = json.loads((old_run / "stages.json").read_text())
    assert all(s in state for s in markers if s != "field_partial"), state
    log = (old_run / "log").read_text()
    assert "running the stage" not in log
    # recognised by the earlier key formula once: the markers now hold today's keys
    keys = _current_keys(old_run)
    assert {s: state[s] for s in markers if s != "field_partial"} == {
        s: keys[s] for s in markers if s != "field_partial"}
    line = next(x for x in log.splitlines() if "earlier release's formula" in x)
    assert set(line.split("stage(s) ")[1].split(" finished")[0].split(", ")) == {
        s for s in markers if s in state}  # field_partial too, while it is kept
    _rerun()
    assert (old_run / "log").read_text().count("earlier release's formula") == 1
    assert _stage_times(old_run) == times


def test_an_old_run_folder_killed_before_fusion_resumes_with_the_same_bytes(old_run):
    files, times = _files(old_run), _stage_times(old_run)
    state = json.loads((old_run / "stages.json").read_text())
    for part in (state, state["provenance"], state["outputs"]):
        for stage in ("fusion", "mesh"):
            part.pop(stage, None)
    (old_run / "stages.json").write_text(json.dumps(state))
    (old_run / "points.ply").unlink()
    (old_run / "mesh.ply").unlink()
    start = time.time_ns()
    _rerun()
    assert _files(old_run) == files
    now = _stage_times(old_run)
    assert {k: now[k] for k in ("mvs1", "field", "guide", "mvs23")} == {
        k: times[k] for k in ("mvs1", "field", "guide", "mvs23")}  # read back, not run
    assert _rewritten(old_run, "fusion", start) and _rewritten(old_run, "mesh", start)


def test_an_old_run_folder_with_width_paper_runs_the_finer_stages_again(old_run_as_made):
    """``width: paper`` changed meaning: the stages before the finer MVS stages are read back,
    the finer stages and everything after them run again."""
    times = _stage_times(old_run_as_made)
    start = time.time_ns()
    _rerun()
    now = _stage_times(old_run_as_made)
    assert {k: now[k] for k in ("mvs1", "field", "guide")} == {
        k: times[k] for k in ("mvs1", "field", "guide")}
    assert _rewritten(old_run_as_made, "mvs23", start)
    assert _rewritten(old_run_as_made, "fusion", start)
    assert not _rewritten(old_run_as_made, "guide", start)
