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
    sampler = MVSGuidedSampler(None, GuidedSamplerConfig(samples_coarse=16, samples_uniform=8,
                                                         samples_fine=8))
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


@pytest.mark.parametrize("host_branch", [True, False])
def test_non_finite_step_changes_nothing(host_branch):
    t = _trainer()
    t.host_branch = host_branch  # False: the device-side path a GPU run takes
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


@pytest.mark.parametrize("host_branch", [True, False])
@pytest.mark.parametrize("clip", [0.0, 1e-3, 1e3])
def test_safe_clip_is_clip_grad_norm_on_finite_gradients(host_branch, clip):
    t = _trainer(grad_clip=clip)
    t.host_branch = host_branch
    t.losses()["total"].backward()
    params = [p for p in t.model.parameters() if p.grad is not None]
    expected = [p.grad.clone() for p in params]
    if clip > 0:
        total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g)
                                                      for g in expected]))
        expected = [g * min(1.0, clip / (float(total) + 1e-6)) for g in expected]
    t._safe_clip(params)
    for p, g in zip(params, expected, strict=True):
        torch.testing.assert_close(p.grad, g)
    if clip == 1e-3:  # the clip binds
        total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(p.grad)
                                                      for p in params]))
        assert abs(float(total) - clip) < 1e-6


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


def test_object_ray_fraction_draws_that_share_inside_the_focus():
    """object_ray_fraction f: f of each step's rays come from the view's focus pixels (the
    dilated masks), the rest stay uniform over the image; 0 keeps the released uniform draw."""
    data = _data()
    V, _, H, W = data.images.shape
    focus = torch.zeros(V, H, W, dtype=torch.bool)
    focus[:, 5:9, 10:14] = True  # 16 of 432 pixels
    focus[2] = False
    focus[2, 0, 0] = True  # a one-pixel focus
    data.focus = focus
    model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]), GridFieldConfig(resolution=12))
    cfg = TrainConfig(mode="volsdf", steps=6, rays=64, object_ray_fraction=0.75)
    sampler = MVSGuidedSampler(None, GuidedSamplerConfig(samples_coarse=16, samples_uniform=8,
                                                         samples_fine=8))
    tr = Trainer(model, data, cfg, sampler=sampler)
    seen = set()
    for _ in range(30):
        rays, pix, t = tr.sample_rays(64)
        inside = focus[int(t)].reshape(-1)[pix]
        assert len(pix) == 64 and int(inside.sum()) >= 48  # 48 drawn inside, some uniform ones too
        assert pix.min() >= 0 and pix.max() < H * W
        seen.add(int(t))
        # the rays go through the drawn pixels
        uv = torch.stack([pix % W, pix // W], -1).float()
        assert torch.allclose(rays.dirs, tr.make_rays(t, uv).dirs)
    assert seen == {0, 1, 2}
    uniform = Trainer(model, data, TrainConfig(mode="volsdf", steps=6, rays=64), sampler=sampler)
    rays, pix, t = uniform.sample_rays(64)
    assert len(torch.unique(pix)) == 64 and uniform.focus_index is None


def test_resume_into_a_field_built_for_another_box_trains_the_loaded_grids(tmp_path):
    """Resuming into a grid field whose box differs from the checkpoint's: the field takes the
    stored grids, and the optimizer is rebuilt on them (not left on the replaced tensors)."""
    a = _trainer(tmp_path / "a")
    a.fit(progress=False)
    torch.manual_seed(1)
    model = GridSDFField(torch.tensor([[-1.1, -0.5, -0.8], [1.0, 0.5, 0.8]]),
                         GridFieldConfig(resolution=12))
    cfg = TrainConfig(mode="volsdf", steps=8, rays=32, checkpoint_every=3)
    sampler = MVSGuidedSampler(None, GuidedSamplerConfig(samples_coarse=16, samples_uniform=8,
                                                         samples_fine=8))
    b = Trainer(model, _data(), cfg, sampler=sampler, out_dir=tmp_path / "a")
    assert model.grid_shape != a.model.grid_shape
    stored = torch.load(b.checkpoint_path(), weights_only=False)
    assert b.load_checkpoint() and b.step == stored["iter_step"] < 8
    assert model.grid_shape == a.model.grid_shape
    torch.testing.assert_close(model.sdf_grid, stored["model_state_dict"]["sdf_grid"])
    in_opt = {id(p) for g in b.optimizer.param_groups for p in g["params"]}
    assert {id(p) for p in model.parameters()} == in_opt
    before = model.sdf_grid.detach().clone()
    b.fit(progress=False)
    assert b.step == 8 and not torch.equal(before, model.sdf_grid.detach())


def test_losses_go_to_tensorboard_when_installed_else_csv_only(tmp_path, monkeypatch):
    """With the tensorboard extra the logged losses are TensorBoard scalars under
    OUT/field/tensorboard as they are made; without it, losses.csv alone, as before."""
    import builtins

    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    t = _trainer(tmp_path / "tb")
    t.fit(progress=False, log_every=2)
    acc = EventAccumulator(str(tmp_path / "tb" / "tensorboard"))
    acc.Reload()
    assert {"train/total", "train/rgb", "train/beta"} <= set(acc.Tags()["scalars"])
    assert [e.step for e in acc.Scalars("train/total")] == [2, 4, 6]
    assert acc.Scalars("train/total")[-1].value == pytest.approx(t.history[-1]["total"])
    real = builtins.__import__

    def no_tensorboard(name, *a, **k):
        if name.startswith(("torch.utils.tensorboard", "tensorboard")):
            raise ImportError(f"No module named {name!r}")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_tensorboard)
    t = _trainer(tmp_path / "csv")
    t.fit(progress=False, log_every=2)
    assert not (tmp_path / "csv" / "tensorboard").exists()
    assert (tmp_path / "csv" / "losses.csv").read_text().startswith("step")
