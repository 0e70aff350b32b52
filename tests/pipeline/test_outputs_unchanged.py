"""Every output byte and every stage key of the presets and modes, against a recorded fingerprint.

Each case of `CASES` reconstructs the same small synthetic sphere (four 64x48 views, three of them
used, a short field run on one thread) through ``svolsdf reconstruct --config``; the sha1 of every
file the run writes (the scene's folder written as ``SCENE`` in config.yaml and views.json; a
torch file by its loaded values, since its zip names its members after the temporary file it was
written to; the field's steps per second left out of losses.csv and the checkpoint), what
OUT/stages.json records of each stage (its output files and its inputs key), and the stage keys of
the case's config (with ``scene.path`` = ``SCENE``, so that they do not depend on where the test
runs) must equal tests/pipeline/data/outputs_fingerprint.json. A refactoring of the pipeline that
changes no result keeps this test passing; one that does change a result must say why in its
commit and record the fingerprint again:

    SVOLSDF_RECORD_FINGERPRINT=1 python -m pytest -q -p no:cacheprovider \
        tests/pipeline/test_outputs_unchanged.py

(which rewrites the JSON and then fails, so that a recording is never mistaken for a pass).
The keys are those of the stages' declarations (`svolsdf.pipeline.keys.stage_keys`), which the
runner marks finished stages with; run folders marked by the earlier formula are recognised by
`svolsdf.pipeline.legacy_keys` (test_old_run_folder.py, test_keys_before_sections.py).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path

import pytest
from tiny_pipeline import cli, make_small_sphere_scene

from svolsdf.config import preset, save_config

pytestmark = pytest.mark.slow

FINGERPRINT = Path(__file__).parent / "data" / "outputs_fingerprint.json"

# files whose bytes change from one run to the next by design (times, the log, the lock) or that
# hold the scene's folder (compared with it replaced) or the run's bookkeeping (compared by part)
_SKIPPED = {"log", "timing.json", ".svolsdf.lock", "stages.json", "run.json"}
# TensorBoard's event files (written when tensorboard is installed) are named after the time and
# the host, and hold the wall-clock time of each value
_SKIPPED_FOLDERS = ("tensorboard",)
_WITH_SCENE_PATH = {"config.yaml", "views.json"}


def _short(cfg) -> None:
    """The case's config shortened for a 64x48 scene: seconds, one thread."""
    cfg.scene.views = [0, 1, 2]
    cfg.threads = 1
    cfg.train.steps = 20
    cfg.train.rays = 32
    cfg.train.checkpoint_every = 10
    cfg.train.anneal_rgb = min(cfg.train.anneal_rgb, 5)
    cfg.field.grid_start_resolution = 16
    cfg.field.grid_resolution = 16
    cfg.mesh.resolution = 24
    cfg.mesh.fit_points = min(cfg.mesh.fit_points, 20)


def _case(name: str, **sets) -> tuple[str, str, dict]:
    return name, sets.pop("preset", "fast"), sets


CASES = [
    _case("fast"),
    _case("draft", preset="draft"),
    # the MLP field of the paper preset; its error-bounded sampler renders for minutes even here
    _case("paper", preset="paper", **{"train.steps": 6, "mesh.method": "poisson",
                                      "train.sampler": "mvs", "guide.mask_dilation": 4}),
    _case("volsdf", **{"train.mode": "volsdf"}),
    _case("mvs-only", **{"train.mode": "mvs-only"}),
    _case("field-mesh-fitted", **{"mesh.method": "field"}),
    _case("tsdf", **{"mesh.method": "tsdf", "mesh.tsdf.fill_holes": 2}),
    _case("watertight", **{"mesh.method": "field", "mesh.watertight": True}),
    _case("finer-stage", **{"mvs.finer_stage_optimization": True}),
    _case("ablation-mse", **{"train.ablation": "mse"}),
    _case("ablation-soft", **{"train.ablation": "soft-consistency-only"}),
    _case("no-masks-colour", **{"scene.use_masks": False, "train.colour_steps": 4}),
]


def case_config(scene: Path | str, preset_name: str, sets: dict):
    """The `Config` of a case for the scene at ``scene``."""
    cfg = preset(preset_name)
    cfg.scene.path = str(scene)
    _short(cfg)
    for dotted, value in sets.items():
        *parents, leaf = dotted.split(".")
        node = cfg
        for p in parents:
            node = getattr(node, p)
        setattr(node, leaf, value)
    return cfg


def recorded_keys(cfg, views) -> dict[str, str]:
    """The stage keys the runner marks a run folder's stages with."""
    from svolsdf.pipeline.keys import stage_keys

    return stage_keys(cfg, views)


def _sha1(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()[:16]


def _timeless(obj):
    """``obj`` (a loaded torch file) with the optimization's speed left out, as JSON-able
    values: a tensor becomes the digest of its dtype, shape and bytes."""
    import torch

    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        return f"{t.dtype}{tuple(t.shape)}:{_sha1(t.view(-1).view(torch.uint8).numpy().tobytes())}"
    if isinstance(obj, dict):
        return {str(k): _timeless(v) for k, v in obj.items() if k not in _SPEED}
    if isinstance(obj, (list, tuple)):
        return [_timeless(v) for v in obj]
    return obj if isinstance(obj, (int, float, str, bool, type(None))) else repr(obj)


# a field's steps per second (losses.csv's column, the checkpoint's history) is the machine's
_SPEED = {"steps_per_s"}


def _content(rel: str, path: Path, scene: Path) -> str:
    """The digest of what a run file holds: its bytes, but for a torch file (whose zip names
    its members after the temporary file it was written to) its loaded values, and for
    losses.csv its columns but the speed."""
    import torch

    if path.suffix == ".pt":
        obj = torch.load(path, map_location="cpu", weights_only=False)
        return _sha1(json.dumps(_timeless(obj), sort_keys=True).encode())
    data = path.read_bytes()
    if rel in _WITH_SCENE_PATH:
        data = data.replace(str(scene).encode(), b"SCENE")
    if path.name == "losses.csv":
        rows = [line.split(",") for line in data.decode().splitlines()]
        keep = [i for i, name in enumerate(rows[0]) if name not in _SPEED]
        data = "\n".join(",".join(r[i] for i in keep) for r in rows).encode()
    return _sha1(data)


def _recorded(outputs: dict | None) -> dict | None:
    """A stage's record of its files (OUT/stages.json "outputs"), a torch file's by its name
    alone (its size and digest follow the temporary name it was written to, whose length
    varies; its content is compared as a file)."""
    if not isinstance(outputs, dict):
        return outputs
    return {f: ("torch file" if f.endswith(".pt") else r) for f, r in outputs.items()}


def fingerprint(out: Path, scene: Path, cfg) -> dict:
    """What a case's run folder must hold: {"files": {path: sha1}, "stages": {stage: {"outputs":
    ..., "inputs": ...}}, "keys": {stage: key}}."""
    files = {}
    for f in sorted(out.rglob("*")):
        rel = f.relative_to(out).as_posix()
        if not f.is_file() or rel in _SKIPPED or any(
                part in _SKIPPED_FOLDERS for part in f.relative_to(out).parts[:-1]):
            continue
        files[rel] = _content(rel, f, scene)
    st = json.loads((out / "stages.json").read_text())
    stages = {s: {"outputs": _recorded(st.get("outputs", {}).get(s)),
                  "inputs": st.get("provenance", {}).get(s, {}).get("inputs")}
              for s in sorted(st) if isinstance(st[s], str)}
    views = json.loads((out / "views.json").read_text())["inputs"]
    placed = copy.deepcopy(cfg)
    placed.scene.path = "SCENE"
    return {"files": files, "stages": stages, "keys": recorded_keys(placed, views)}


def _differences(want: dict, got: dict) -> list[str]:
    """The entries of two fingerprints that differ, named (``files/points.ply``)."""
    diff = []
    for part in ("files", "stages", "keys"):
        a, b = want.get(part, {}), got.get(part, {})
        diff += [f"{part}/{k}: {a.get(k)} -> {b.get(k)}" for k in sorted(set(a) | set(b))
                 if a.get(k) != b.get(k)]
    return diff


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    return make_small_sphere_scene(tmp_path_factory.mktemp("fp") / "scene")


def run_case(scene: Path, folder: Path, preset_name: str, sets: dict) -> tuple[Path, object]:
    """``svolsdf reconstruct`` of a case into FOLDER/run; (the run folder, the config)."""
    cfg = case_config(scene, preset_name, sets)
    folder.mkdir(parents=True, exist_ok=True)
    save_config(cfg, folder / "case.yaml")
    cli(["reconstruct", "-o", folder / "run", "--config", folder / "case.yaml",
         "--no-progress"])
    return folder / "run", cfg


def test_outputs_and_keys_match_the_recorded_fingerprint(sphere_scene, tmp_path):
    recording = os.environ.get("SVOLSDF_RECORD_FINGERPRINT") == "1"
    want = {} if recording else json.loads(FINGERPRINT.read_text())
    got = {}
    for name, preset_name, sets in CASES:
        out, cfg = run_case(sphere_scene, tmp_path / name, preset_name, sets)
        got[name] = fingerprint(out, sphere_scene, cfg)
        if not recording:
            assert got[name] == want[name], (name, _differences(want[name], got[name]))
    if recording:
        FINGERPRINT.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
        pytest.fail(f"recorded {FINGERPRINT}; run again without SVOLSDF_RECORD_FINGERPRINT")
    assert set(want) == set(got)
