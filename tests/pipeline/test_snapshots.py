"""Surface snapshots during the field's optimization (train.snapshot_every) and their figure."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from tests.field.analytic import SphereSDF

from svolsdf.config import preset
from svolsdf.io.ply import read_ply
from svolsdf.pipeline.keys import stage_keys
from svolsdf.pipeline.snapshots import snapshot_figure, snapshot_writer


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from svolsdf.scene.loaders import load_scene
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    root = make_synthetic_scene(tmp_path_factory.mktemp("s") / "synth",
                                SynthConfig(views=3, width=96, height=72, gt_points=2000,
                                            supersample=1, mesh_resolution=6.0, object="sphere"))
    return load_scene(root)


class _Growing(SphereSDF):
    """A sphere whose radius a test changes between snapshots."""

    def sdf(self, x):
        return (x - self.center).norm(dim=-1) - self.r


def _context(tmp_path, scene, every: int):
    cfg = preset("fast")
    cfg.train.snapshot_every = every
    return SimpleNamespace(cfg=cfg, dir=SimpleNamespace(field_dir=tmp_path / "field"),
                           load=lambda: scene, device=torch.device("cpu"),
                           field_bounds=lambda: torch.tensor([[-1.0] * 3, [1.0] * 3]))


def test_snapshots_at_the_given_steps_and_their_figure(tmp_path, scene):
    model = _Growing(radius=0.3)
    p = _context(tmp_path, scene, every=50)
    snap = snapshot_writer(p, model, start=0)
    for step in range(1, 151):
        if step == 100:
            model.r = 0.6
        snap(step)
    folder = tmp_path / "field" / "snapshots"
    assert sorted(f.name for f in folder.glob("*.ply")) == [
        "step_000000.ply", "step_000050.ply", "step_000100.ply", "step_000150.ply"]
    # world units: the unit sphere's radius times the scene's scale, about its centre
    norm = scene.normalization
    for name, r in (("step_000050.ply", 0.3), ("step_000150.ply", 0.6)):
        v = torch.as_tensor(read_ply(folder / name)["points"], dtype=torch.float64)
        unit = norm.to_unit(v)
        assert len(v) > 50 and unit.norm(dim=-1).sub(r).abs().max() < 0.05
    png = snapshot_figure(folder, scene.cameras, tmp_path / "snaps.png")
    from PIL import Image

    im = np.asarray(Image.open(png))
    assert im.shape[0] > 100 and im.std() > 5  # four shaded panels, not a blank page


def test_no_snapshots_by_default_and_no_key_changes(tmp_path, scene):
    p = _context(tmp_path, scene, every=0)
    assert snapshot_writer(p, SphereSDF(radius=0.3), start=0) is None
    assert not (tmp_path / "field").exists()
    a, b = preset("fast"), preset("fast")
    b.train.snapshot_every = 10
    for c in (a, b):
        c.scene.path = "scene"
    assert stage_keys(a, [0, 1, 2]) == stage_keys(b, [0, 1, 2])


@pytest.mark.slow
def test_pipeline_writes_snapshots_and_the_figure(tmp_path):
    """A run with train.snapshot_every: the field stage leaves the snapshots (the start and
    every N steps) and their figure; the run's results do not depend on it."""
    from tiny_pipeline import make_tiny_scene, tiny_cfg

    from svolsdf.pipeline import Pipeline

    cfg = tiny_cfg(make_tiny_scene(tmp_path / "scene"), steps=40)
    cfg.train.snapshot_every = 20
    Pipeline(cfg, tmp_path / "out", progress=False).run()
    snaps = tmp_path / "out" / "field" / "snapshots"
    assert sorted(f.name for f in snaps.glob("*.ply")) == [
        "step_000000.ply", "step_000020.ply", "step_000040.ply"]
    assert (snaps / "snapshots.png").stat().st_size > 1000
    assert len(read_ply(snaps / "step_000040.ply")["faces"]) > 50
