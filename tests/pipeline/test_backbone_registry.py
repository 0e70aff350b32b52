"""The backbone registry (`svolsdf.mvs.backbone.register_backbone`): a backbone registered here,
in the test file alone, is accepted by the config and runs as the MVS stages of a tiny pipeline;
an unregistered name is refused naming the option and the registered ones; a withdrawn name is
refused again."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from tiny_pipeline import make_tiny_scene, tiny_cfg

from svolsdf.config import choices, load_config, preset, validate_config
from svolsdf.errors import InputError
from svolsdf.mvs.backbone import (
    MVSBackbone,
    available_backbones,
    get_backbone,
    register_backbone,
    stage_cameras,
    unregister_backbone,
    volume_from_prob,
)
from svolsdf.pipeline import Pipeline
from svolsdf.pipeline.keys import stage_keys


@dataclass
class _ToyConfig:
    """The keywords `svolsdf.pipeline.builders.backbone_kwargs` gives a backbone other than the
    plane sweep."""

    ndepths: tuple = (8, 4, 4)
    width: str = "paper"
    inverse_depth: bool = False
    max_sources: int = 4


class _ToyBackbone(MVSBackbone):
    """Stage 1: every pixel at the middle of its view's depth range; stages 2-3: the depth that
    centres them (the guide, else the previous stage's), so the cascade ends on the guide."""

    config_class = _ToyConfig

    def __init__(self, **cfg):
        self.config = _ToyConfig(**cfg)

    def stage(self, k, scene, ref_ids=None, guide_depth=None, prev=None):
        out = []
        for vid in ref_ids if ref_ids is not None else scene.view_ids:
            cams = stage_cameras(scene.cameras[[scene.index(vid)]], k)
            H, W = cams.height, cams.width
            near, far = (float(x) for x in scene.depth_range[scene.index(vid)])
            if k == 1:
                centre = torch.full((H, W), (near + far) / 2)
            else:
                c = guide_depth[vid] if guide_depth and vid in guide_depth else prev[vid].depth
                centre = F.interpolate(c[None, None].float(), size=(H, W), mode="nearest")[0, 0]
            D = self.config.ndepths[k - 1]
            step = (far - near) / (4 * D)
            offsets = (torch.arange(D) - D // 2).float() * step
            depths = centre[None] + offsets[:, None, None]
            prob = torch.zeros(D, H, W)
            prob[D // 2] = 1.0
            out.append(volume_from_prob(prob, depths, cams, vid, k))
        return out


@pytest.fixture(autouse=True, scope="module")
def _toy_registered():
    """The toy is registered while this module's tests run, and withdrawn after them (the
    command line's help, built once, names the backbones registered when it was built)."""
    register_backbone("test-toy")(_ToyBackbone)
    yield
    unregister_backbone("test-toy")


def test_builtin_backbones_and_the_toy_are_registered():
    names = available_backbones()
    assert {"planesweep", "casmvsnet", "patchmatchnet", "test-toy"} <= set(names)
    assert names == sorted(names)
    assert choices("mvs.backbone") == tuple(names)
    assert isinstance(get_backbone("test-toy"), _ToyBackbone)


def test_a_registered_backbone_is_a_valid_choice_and_others_are_refused():
    cfg = preset("fast")
    cfg.mvs.backbone = "test-toy"
    validate_config(cfg)
    cfg.mvs.backbone = "no-such-backbone"
    with pytest.raises(InputError, match=r"mvs\.backbone = 'no-such-backbone': expected one of "
                                         r"'casmvsnet', 'patchmatchnet', 'planesweep'"):
        validate_config(cfg)
    with pytest.raises(InputError, match="unknown MVS backbone 'no-such-backbone'"):
        get_backbone("no-such-backbone")


def test_a_withdrawn_backbone_is_refused():
    register_backbone("test-withdrawn")(_ToyBackbone)
    assert "test-withdrawn" in available_backbones()
    unregister_backbone("test-withdrawn")
    assert "test-withdrawn" not in available_backbones()
    with pytest.raises(InputError, match="unknown MVS backbone 'test-withdrawn'"):
        get_backbone("test-withdrawn")


@pytest.mark.slow
def test_a_registered_backbone_runs_as_the_mvs_stages(tmp_path_factory):
    """The toy backbone's volumes are the run's: its final depth is the guide's (at stage 2's
    resolution); its name and config enter the MVS stages' keys."""
    scene = make_tiny_scene(tmp_path_factory.mktemp("syn") / "scene")
    out = tmp_path_factory.mktemp("run")
    cfg = tiny_cfg(scene, steps=40)
    cfg.mvs.backbone = "test-toy"
    cfg.fusion.unguided = False
    p = Pipeline(cfg, out, progress=False)
    p.run()
    assert "backbone: test-toy" in (out / "config.yaml").read_text()
    sweep = load_config(out / "config.yaml")
    sweep.mvs.backbone = "planesweep"
    views = p.views
    toy_keys, sweep_keys = stage_keys(cfg, views), stage_keys(sweep, views)
    assert toy_keys["mvs1"] != sweep_keys["mvs1"] and toy_keys["mvs23"] != sweep_keys["mvs23"]
    v = json.loads((out / "views.json").read_text())["inputs"][0]
    guide = np.load(out / "field" / "render_depth" / f"{v}.npy")
    final = np.load(out / "depth" / f"{v}.npy")
    assert final.shape == guide.shape
    # the guide, resampled to stage 2's half size and back
    assert np.median(np.abs(final - guide) / guide) < 1e-3
    assert (out / "points.ply").is_file() and (out / "mesh.ply").is_file()
