"""The declared stages (`svolsdf.pipeline.stages`): they consume only stages before them, and
in a run every stage's `run` and `load` is called by the runner alone (no stage reaches another
for its input)."""

from __future__ import annotations

import sys

from tiny_pipeline import cli, copy_run, make_small_sphere_scene

from svolsdf.pipeline.keys import STAGES
from svolsdf.pipeline.stages import PIPELINE_STAGES, Stage


def test_stages_are_in_order_and_consume_only_earlier_ones():
    assert [s.name for s in PIPELINE_STAGES] == list(STAGES)
    for i, s in enumerate(PIPELINE_STAGES):
        assert set(s.consumes) <= set(STAGES[:i]), s.name


def _callers(argv) -> list[tuple[str, str, str]]:
    """(stage, method, caller) of each `Stage.run` and `Stage.load` call while ``argv`` runs."""
    calls = []

    def prof(frame, event, arg):
        if event != "call" or frame.f_code.co_name not in ("run", "load"):
            return
        me = frame.f_locals.get("self")
        if isinstance(me, Stage) and frame.f_back is not None:
            calls.append((me.name, frame.f_code.co_name, frame.f_back.f_code.co_name))

    sys.setprofile(prof)
    try:
        cli(argv)
    finally:
        sys.setprofile(None)
    return calls


def test_only_the_runner_runs_or_loads_a_stage(tmp_path):
    scene = make_small_sphere_scene(tmp_path / "scene")
    (tmp_path / "c.yaml").write_text(
        f"scene: {{path: {scene}, views: [0, 1, 2]}}\n"
        "field: {grid_start_resolution: 16, grid_resolution: 16}\n"
        "mesh: {resolution: 24, method: field, fit_points: 0}\nfusion: {unguided: true}\n"
        "train: {rays: 32, checkpoint_every: 0, steps: 4}\n")
    argv = ["reconstruct", "-o", tmp_path / "run", "--config", tmp_path / "c.yaml",
            "--no-progress"]
    ran = _callers(argv)
    assert {(s, m) for s, m, _ in ran} == {(s, "run") for s in STAGES}
    copy_run(tmp_path / "run", tmp_path / "again")
    argv[2] = tmp_path / "again"
    loaded = _callers(argv)
    assert {(s, m) for s, m, _ in loaded} == {(s, "load") for s in STAGES}
    assert {c for *_, c in ran + loaded} == {"_drive"}
