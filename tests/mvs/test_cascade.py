"""The cascade: guide depth centring stages 2-3 (docs/method.md 6.1, 2.5), outputs on disk (the
``svolsdf mvs`` job and command: tests/commands/test_mvs.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from tests.mvs.synth import plane_scene

from svolsdf.errors import InputError
from svolsdf.mvs.cascade import (
    combined_confidence,
    run_and_save_cascade,
    run_cascade,
    save_cascade,
)
from svolsdf.mvs.hypotheses import base_interval
from svolsdf.mvs.planesweep import PlaneSweepBackbone
from svolsdf.mvs.volume import ProbabilityVolume

RANGE = (2.5, 6.0)


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_guide_centres_stage2_and_stage3_follows_stage2():
    scene, gt = plane_scene(48, 36, depth_range=RANGE)
    guide = {v: gt[v] + 0.05 for v in scene.view_ids}  # a guide 5 cm behind the surface
    res = run_cascade(PlaneSweepBackbone(), scene, guide_depth=guide, stages=(1, 2, 3))
    assert sorted(res) == [1, 2, 3]
    for v2, v3 in zip(res[2], res[3], strict=True):
        g = F.interpolate(guide[v2.view_id][None, None], size=v2.depth.shape, mode="bilinear",
                          align_corners=False)[0, 0]
        assert torch.allclose(v2.depths.mean(0), g, atol=1e-4)  # centred on the guide
        c3 = F.interpolate(v2.depth[None, None], size=v3.depth.shape, mode="bilinear",
                           align_corners=False)[0, 0]
        assert torch.allclose(v3.depths.mean(0), c3, atol=1e-4)  # then on stage 2's depth
        # stage 2 moves from the guide (0.05 off) to the surface, stage 3 refines it
        e2 = (v2.depth - F.interpolate(gt[v2.view_id][None, None], size=v2.depth.shape)[0, 0])
        # the plane sweep runs at 2x the working size (mvs_size): ground truth by nearest
        e3 = (v3.depth - F.interpolate(gt[v3.view_id][None, None], size=v3.depth.shape)[0, 0])
        e3 = e3.abs().median()
        assert float(e2.abs().median()) < 0.035 and float(e3) < 0.02
    # without stage 1, a guide alone starts the cascade at stage 2
    res23 = run_cascade(PlaneSweepBackbone(), scene, guide_depth=guide, stages=(2, 3))
    assert sorted(res23) == [2, 3]
    assert torch.allclose(res23[2][0].depths, res[2][0].depths)


def test_prev_resumes_and_stage_order_is_checked():
    scene, _ = plane_scene(32, 24, depth_range=RANGE)
    bb = PlaneSweepBackbone()
    r1 = run_cascade(bb, scene, stages=(1,))
    r23 = run_cascade(bb, scene, stages=(2, 3), prev={v.view_id: v for v in r1[1]})
    full = run_cascade(bb, scene)
    assert torch.allclose(r23[3][2].depth, full[3][2].depth, atol=1e-5)
    with pytest.raises(ValueError, match="increasing"):
        run_cascade(bb, scene, stages=(3, 2))
    with pytest.raises(InputError, match="previous stage"):
        run_cascade(bb, scene, stages=(2,))


def test_save_cascade_files_and_roundtrip(tmp_path):
    scene, _ = plane_scene(32, 24, depth_range=RANGE)
    res = run_cascade(PlaneSweepBackbone(), scene, ref_ids=[0, 2])
    pictures = []
    files = save_cascade(res, tmp_path, picture=lambda d, p: pictures.append((d.shape, p)))
    assert sorted(files) == [0, 2]
    for k in (1, 2, 3):
        for vid in (0, 2):
            v = ProbabilityVolume.load(tmp_path / "mvs" / f"stage{k}" / f"{vid}.npz")
            orig = res[k][[0, 2].index(vid)]
            assert v.stage == k and v.view_id == vid
            assert torch.allclose(v.depths, orig.depths)
            assert torch.allclose(v.prob, orig.prob, atol=2e-3)  # stored as float16
            assert torch.allclose(v.prob.sum(0), torch.ones(v.depth.shape), atol=1e-5)
    d = np.load(files[0]["depth"])
    assert d.dtype == np.float32 and d.shape == (48, 64)  # stage 3 at the MVS size, 2x
    assert np.allclose(d, res[3][0].depth.numpy())
    conf = np.load(files[0]["confidence"])
    expect = combined_confidence([res[k][0] for k in (1, 2, 3)], 64, 48)
    assert np.allclose(conf, expect.numpy()) and conf.max() <= 1 + 1e-6
    assert [p.name for _, p in pictures] == ["0.png", "2.png"]


@pytest.mark.parametrize("guided", [False, True])
def test_one_view_at_a_time_writes_what_the_whole_cascade_writes(tmp_path, guided):
    """`run_and_save_cascade` (the pipeline's stages 2-3, one reference view in memory at a
    time) gives the files of `run_cascade` + `save_cascade` over all views."""
    scene, gt = plane_scene(32, 24, depth_range=RANGE)
    bb = PlaneSweepBackbone()
    vols1 = run_cascade(bb, scene, stages=(1,))[1]
    prev = {v.view_id: v for v in vols1}
    guide = {v: gt[v] + 0.05 for v in scene.view_ids} if guided else None
    whole = run_cascade(bb, scene, guide_depth=guide, stages=(2, 3), prev=prev)
    save_cascade({1: vols1, **whole}, tmp_path / "a")
    depths = run_and_save_cascade(PlaneSweepBackbone(), scene, tmp_path / "b", stages=(2, 3),
                                  guide_depth=guide, prev=prev, earlier={1: vols1})
    assert sorted(depths) == sorted(scene.view_ids)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*.np*"))
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*.np*"))
    assert files_a == files_b and len(files_a) == 3 * 3 + 2 * 3
    for f in files_a:
        if f.suffix == ".npy":
            np.testing.assert_array_equal(np.load(tmp_path / "a" / f), np.load(tmp_path / "b" / f))
        else:
            a, b = np.load(tmp_path / "a" / f), np.load(tmp_path / "b" / f)
            for k in a.files:
                np.testing.assert_array_equal(a[k], b[k])
    for v in whole[3]:
        torch.testing.assert_close(depths[v.view_id], v.depth.float())


def test_combined_confidence_is_the_product():
    scene, _ = plane_scene(32, 24, depth_range=RANGE)
    res = run_cascade(PlaneSweepBackbone(), scene, ref_ids=[1])
    vols = [res[k][0] for k in (1, 2, 3)]
    c = combined_confidence(vols, 32, 24)
    up = [F.interpolate(v.confidence[None, None], size=(24, 32), mode="bilinear",
                        align_corners=False)[0, 0] for v in vols]
    assert torch.allclose(c, up[0] * up[1] * up[2], atol=1e-6)


def test_interval_matches_method_constants():
    # DTU: Δ̄ = 506.15 / 192 = 2.6362 (docs/method.md 2.5)
    assert base_interval(425.0, 425.0 + 2.65 * 191) == pytest.approx(2.6362, abs=1e-4)
