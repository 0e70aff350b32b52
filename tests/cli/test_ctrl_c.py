"""Ctrl-C in every stage of a real `svolsdf reconstruct` process: each SIGINT ends the run with
status 130 and one line, no stage is marked finished over a half-written or stale output, and the
rerun resumes; the last rerun completes with the mesh asked for (docs/run-folder.md "Ctrl-C in any
stage")."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import svolsdf
from svolsdf.pipeline import STAGES, RunDir
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

#: the 64x48 scene's seconds-long run, every stage of the fast preset (the unguided stages 2-3
#: and the Poisson mesh included); one torch thread, so that this process's polling keeps up
CONFIG = ("field: {grid_start_resolution: 16, grid_resolution: 16}\n"
          "mesh: {resolution: 24}\nthreads: 1\n"
          "train: {rays: 32, checkpoint_every: 10, steps: 30}\n")


def _marked(out: Path) -> set[str]:
    try:
        st = json.loads((out / "stages.json").read_text())
    except (OSError, ValueError):
        return set()
    return {k for k in st if k in STAGES or k == "field_partial"}


def _log(out: Path) -> str:
    return (out / "log").read_text() if (out / "log").is_file() else ""


def _newer(path: Path, t: float) -> bool:
    """A file at ``path`` (a glob pattern's first match) written after ``t`` (time.time())."""
    return any(p.stat().st_mtime > t for p in path.parent.glob(path.name))


def _from(stage: str):
    """Wait for: ``stage`` or a later one newly marked finished (the next one has begun)."""
    later = set(STAGES[STAGES.index(stage):])
    return lambda out, before, t: bool((_marked(out) - before["marked"]) & later)


def _started(out, before, t) -> bool:
    """Wait for: the run has loaded the scene and begun its stages."""
    return _log(out).count("svolsdf.pipeline: scene ") > before["log"].count(
        "svolsdf.pipeline: scene ")


#: (what the signal should interrupt, when to send it: a condition on the run folder, then
#: seconds to wait, past the end of the stage before). A condition is met by a later stage too
#: if this one went by unseen.
POINTS = [
    ("mvs1 as it starts", _started, 0.0),
    ("field as it starts", lambda out, before, t: bool(
        (_marked(out) - before["marked"]) & {"field_partial", *STAGES[1:]}), 0.0),
    ("field after a checkpoint", lambda out, before, t: _newer(
        out / "field" / "checkpoint.pt", t) or bool(_marked(out) - before["marked"]), 0.0),
    ("guide as it starts", _from("field"), 0.05),
    ("mvs23 as it starts", _from("guide"), 0.05),
    ("unguided as it starts", _from("mvs23"), 0.05),
    ("fusion as it starts", _from("unguided"), 0.02),
    ("mesh as it starts (pycolmap's import)", _from("fusion"), 0.05),
    # the earlier stages are finished: the run reads them back and meshes
    ("mesh as it meshes", _started, 1.0),
]


def _check_folder(out: Path, stopped: str) -> None:
    """No stage is marked over files that differ from those it finished with; the stage that
    stopped is not marked; no fallback mesh."""
    d = RunDir(out)
    st = d.state()
    for stage in _marked(out) - {"field_partial"}:
        assert d.changed_output(stage) is None, (stage, d.changed_output(stage))
        assert st["outputs"][stage], stage  # a record of its files
    assert stopped not in st, (stopped, sorted(_marked(out)))
    timing = json.loads((out / "timing.json").read_text()) if (out / "timing.json").is_file() \
        else {}
    assert "failed" not in str(timing.get("mesh", {}).get("mesh_source", ""))


@pytest.mark.slow  # nine interrupted processes and a finished one: ~1 minute on two cores
def test_ctrl_c_in_every_stage_exits_130_marks_nothing_half_done_and_resumes(tmp_path):
    scene = tmp_path / "scene"
    make_synthetic_scene(scene, SynthConfig(views=3, width=64, height=48, seed=2, supersample=1,
                                            gt_points=5000))
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"scene: {{path: {scene}}}\n" + CONFIG)
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(Path(svolsdf.__file__).parents[1]))
    argv = [sys.executable, "-m", "svolsdf", "reconstruct", "-o", str(out), "--config",
            str(cfg), "--no-progress"]
    stopped_in = []
    for what, ready, delay in POINTS:
        before, t = {"marked": _marked(out), "log": _log(out)}, time.time()
        p = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True,
                             # a shell's background job ignores SIGINT and its children inherit
                             # that: give the run the default, as a terminal does
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        while p.poll() is None and not ready(out, before, t):
            assert time.time() - t < 120, f"{what}: not reached in 2 minutes"
            time.sleep(0.01)
        time.sleep(delay)
        if p.poll() is not None and what == POINTS[-1][0]:  # a fast machine's mesh is done
            assert p.returncode == 0, p.communicate()[1][-3000:]
            break
        assert p.poll() is None, f"{what}: the run ended before the signal"
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
        last = err.strip().splitlines()[-1] if err.strip() else ""
        assert p.returncode == 130, f"{what}: status {p.returncode}\n{err[-3000:]}"
        assert last.startswith("interrupted"), f"{what}: {last}"
        assert "Traceback" not in err and "Exception ignored" not in err, f"{what}:\n{err}"
        # "interrupted: stage S stopped", or "interrupted after stage S finished" (between two)
        stage = last.split("stage ")[1].split()[0] if "stage " in last else "setup"
        stopped_in.append(stage)
        _check_folder(out, stage if "stopped" in last else "none")
    # the signals reached the stages they were sent to, or one a little later
    assert {"mvs1", "field", "mesh"} <= set(stopped_in), stopped_in
    p = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert _marked(out) >= set(STAGES), sorted(_marked(out))
    _check_folder(out, "none")
    timing = json.loads((out / "timing.json").read_text())
    assert timing["mesh"]["mesh_source"] == "poisson"
    if "field" in stopped_in:  # stopped after a checkpoint: continued from it
        assert "resumed from" in _log(out)
