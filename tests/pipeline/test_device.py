"""The pipeline's device reaches every stage: the MVS backbone, the field (trainer and prior),
rendering, fusion and meshing all receive the device `resolve_device` returned.

No GPU is needed: the resolved device is replaced by ``cpu:0``, a device object distinct from
``cpu`` on which real work still runs, and spies record the device each component is given."""

from __future__ import annotations

import pytest
import torch

from svolsdf.config import preset
from svolsdf.pipeline import Pipeline
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

MARK = torch.device("cpu", 0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("dev") / "scene"
    return make_synthetic_scene(d, SynthConfig(views=3, width=96, height=72, seed=3,
                                               supersample=1, gt_points=2000,
                                               mesh_resolution=6.0))


def _cfg(scene):
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    cfg.device = "cpu"
    cfg.train.steps = 20
    cfg.train.rays = 128
    cfg.train.checkpoint_every = 1000
    cfg.field.grid_start_resolution = 16
    cfg.field.grid_resolution = 24
    cfg.mesh.resolution = 32
    return cfg


def test_every_stage_receives_the_resolved_device(scene, tmp_path, monkeypatch):
    import svolsdf.fusion.filter as filter_mod
    import svolsdf.fusion.mesh_ops as mesh_mod
    import svolsdf.mvs.backbone as backbone_mod
    import svolsdf.optimize.trainer as trainer_mod
    import svolsdf.pipeline.loaded_run as run_mod
    import svolsdf.prior.consistency as prior_mod
    import svolsdf.render.rays as rays_mod
    from svolsdf.scene.cameras import Cameras

    seen: dict[str, list] = {}

    def record(name, value):
        seen.setdefault(name, []).append(value)

    monkeypatch.setattr(run_mod, "resolve_device", lambda name: MARK)

    get_backbone = backbone_mod.get_backbone

    def spy_backbone(name, weights=None, device=None, **cfg):
        bb = get_backbone(name, weights=weights, device=device, **cfg)
        record("backbone", device)
        record("backbone_runs_on", bb.device)
        return bb

    monkeypatch.setattr(backbone_mod, "get_backbone", spy_backbone)

    class SpyTrainer(trainer_mod.Trainer):
        def __init__(self, *a, device=None, **kw):
            record("field", device)
            super().__init__(*a, device=device, **kw)

    monkeypatch.setattr(trainer_mod, "Trainer", SpyTrainer)

    class SpyPrior(prior_mod.MVSPrior):
        def __init__(self, *a, device=None, **kw):
            record("prior", device)
            super().__init__(*a, device=device, **kw)

    monkeypatch.setattr(prior_mod, "MVSPrior", SpyPrior)

    # rendering: the cameras the renderer casts rays from were moved to the device
    cams_to = Cameras.to

    def spy_to(self, device=None, dtype=None):
        out = cams_to(self, device=device, dtype=dtype)
        out._moved_to = device
        return out

    monkeypatch.setattr(Cameras, "to", spy_to)
    rays_from_cameras = rays_mod.rays_from_cameras

    def spy_rays(cams, *a, **kw):
        if hasattr(cams, "_moved_to"):  # the renderer's; the trainer builds its rays itself
            record("render", cams._moved_to)
        return rays_from_cameras(cams, *a, **kw)

    monkeypatch.setattr(rays_mod, "rays_from_cameras", spy_rays)

    fuse = filter_mod.fuse_depth_maps

    def spy_fuse(*a, device=None, **kw):
        record("fusion", device)
        return fuse(*a, device=device, **kw)

    monkeypatch.setattr(filter_mod, "fuse_depth_maps", spy_fuse)

    colors_from_fn = mesh_mod.colors_from_fn

    def spy_colors(*a, device=None, **kw):
        record("mesh", device)
        return colors_from_fn(*a, device=device, **kw)

    monkeypatch.setattr(mesh_mod, "colors_from_fn", spy_colors)
    import svolsdf.fusion.meshing as meshing_mod

    poisson = meshing_mod.poisson_mesh

    def spy_poisson(*a, device=None, **kw):  # the fast preset's mesh: the field's gradient
        record("mesh", device)
        return poisson(*a, device=device, **kw)

    monkeypatch.setattr(meshing_mod, "poisson_mesh", spy_poisson)
    pipe = Pipeline(_cfg(scene), tmp_path / "run", progress=False)
    pipe.run()
    assert pipe.device == MARK
    for stage in ("backbone", "field", "prior", "render", "fusion", "mesh"):
        assert seen.get(stage), f"{stage}: never built"
        assert all(d == MARK for d in seen[stage]), f"{stage} received {seen[stage]}"
    assert all(d == MARK for d in seen["backbone_runs_on"])
    assert (tmp_path / "run" / "points.ply").is_file() and (tmp_path / "run" / "mesh.ply").is_file()


@pytest.mark.parametrize("name", ["planesweep", "casmvsnet", "patchmatchnet"])
def test_every_backbone_takes_a_device(name):
    from svolsdf.mvs.backbone import backbone_config_class, takes_device

    assert takes_device(name)
    conf = backbone_config_class(name)
    if name != "planesweep":  # the networks: a config field (the CPU unless told)
        assert conf().device == "cpu"


def test_planesweep_runs_where_it_is_told(scene):
    from svolsdf.mvs.backbone import get_backbone
    from svolsdf.scene.loaders import load_scene

    s = load_scene(scene, views=[0, 1, 2])
    bb = get_backbone("planesweep", device=MARK, ndepths=(16, 8, 8), scale=1.0)
    assert bb.device == MARK
    (vol,) = bb.stage(1, s, ref_ids=[0])
    assert vol.depth.shape == (18, 24) and torch.isfinite(vol.depth).all()
    assert get_backbone("planesweep").device == torch.device("cpu")
