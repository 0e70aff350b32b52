"""Trainer: checkpoint/resume gives the same parameters as an uninterrupted run; NaN-safe steps;
loss log; beta anneal."""

from __future__ import annotations

import math

import pytest
import torch

from svolsdf.config import TrainConfig
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.optimize.trainer import TrainData, Trainer
from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler
from svolsdf.scene.cameras import Cameras


def _data(V=3, W=24, H=18):
    torch.manual_seed(0)
    K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]]).expand(V, 3, 3).clone()
    w2c = torch.eye(4).repeat(V, 1, 1)
    for i in range(V):
        a = (i - 1) * 0.3
        R = torch.tensor([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
        w2c[i, :3, :3] = R
        w2c[i, :3, 3] = torch.tensor([0, 0, 2.5])
    cams = Cameras(K, w2c, W, H)
    images = torch.rand(V, 3, H, W)
    return TrainData(images, cams, torch.tensor([[1.5, 3.5]]).expand(V, 2).clone())


def _trainer(out_dir=None, **kw):
    torch.manual_seed(1)
    model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]), GridFieldConfig(resolution=12))
    cfg = TrainConfig(mode="volsdf", steps=6, rays=32, checkpoint_every=3, **kw)
    sampler = MVSGuidedSampler(None, GuidedSamplerConfig(n_coarse=16, n_uniform=8, n_fine=8))
    return Trainer(model, _data(), cfg, sampler=sampler, out_dir=out_dir)


def test_resume_matches_uninterrupted_run(tmp_path):
    a = _trainer(tmp_path / "a")
    a.fit(progress=False)
    b = _trainer(tmp_path / "b")

    def kill(step):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # killed right after the step-3 checkpoint
        b.fit(progress=False, on_checkpoint=kill)
    assert (tmp_path / "b" / "checkpoint.pt").is_file()
    c = _trainer(tmp_path / "b")
    assert c.load_checkpoint() and c.step == 3
    c.fit(progress=False)
    assert c.step == 6
    for (n, p), (_, q) in zip(a.model.named_parameters(), c.model.named_parameters(), strict=True):
        torch.testing.assert_close(p, q, msg=n)
    assert (tmp_path / "a" / "losses.csv").read_text().startswith("step")


def test_non_finite_step_changes_nothing():
    t = _trainer()
    before = [p.detach().clone() for p in t.model.parameters()]
    real = t.losses

    def nan_losses():
        terms = real()
        terms["total"] = terms["total"] * float("nan")
        return terms

    t.losses = nan_losses
    t.train_step()
    for p, q in zip(before, t.model.parameters(), strict=True):
        assert torch.equal(p, q.detach())
    t.losses = real
    t.train_step()
    after = list(t.model.parameters())
    assert any(not torch.equal(p, q.detach()) for p, q in zip(before, after, strict=True))


@pytest.mark.parametrize("start", [0.0, 0.05])
def test_beta_anneal(start):
    t = _trainer(beta_start=start, beta_end=0.01)
    b0 = float(t.model.beta)
    t.fit(progress=False)
    if start > 0:  # log-linear from start towards end, not learned
        expect = 0.05 * (0.01 / 0.05) ** (5 / 6)
        assert float(t.model.beta) == pytest.approx(expect, rel=1e-3)
    else:
        assert float(t.model.beta) != b0  # learned
