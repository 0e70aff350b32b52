"""A training step has no device-host synchronisation (issue 4's GPU target), checked on CPU
with `tests/sync_detector.py` for the fast preset (grid field, MVS-guided sampler, MVS prior)
and the paper preset (VolSDF MLP, error-bounded sampler with one iteration in training)."""

from __future__ import annotations

import pytest
import torch
from test_trainer import _data

from svolsdf.config import TrainConfig
from svolsdf.field.background import BackgroundConfig, NeRFPlusPlusBackground
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.optimize.trainer import Trainer
from svolsdf.prior.consistency import MVSPrior
from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler
from svolsdf.render.samplers import ErrorBoundSampler, ErrorBoundSamplerConfig
from svolsdf.scene.scene import Normalization
from sync_detector import SyncDetector


def _prior(data, D=8):
    """Stage-1-like volumes: planes on [1.5, 3.5], probability peaked at depth 2.0."""
    cams = data.cameras
    H, W = cams.height, cams.width
    vols = []
    for i in range(len(cams)):
        depths = torch.linspace(1.5, 3.5, D)[:, None, None].expand(D, H, W).clone()
        prob = torch.softmax(-((depths - 2.0) ** 2) / 0.05, 0)
        vols.append(ProbabilityVolume(depths, prob, (prob * depths).sum(0), torch.ones(H, W),
                                      cams[[i]], i))
    return MVSPrior(vols, Normalization(torch.zeros(3, dtype=torch.float64), 1.0))


def _trainer(kind: str, background: bool = False):
    torch.manual_seed(0)
    data = _data()
    prior = _prior(data)
    if kind == "fast":  # the fast preset's pieces: grid field, guided sampler, annealed beta
        model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]),
                             GridFieldConfig(resolution=12,
                                             sphere_clamp_scale=None if background else 20.0))
        sampler = MVSGuidedSampler(prior, GuidedSamplerConfig(samples_coarse=16, samples_uniform=8,
                                                              samples_fine=8))
        # (the CPU's shortcuts on: host_branch False must leave them out)
        cfg = TrainConfig(steps=4, rays=32, beta_start=0.05, anneal_rgb=2, smooth_weight=0.1,
                          colour_min_weight=1e-4, prior_floor=1e-4)
    else:  # the paper preset's pieces: MLP, error-bounded sampler (1 iteration in training)
        model = VolSDFField(VolSDFFieldConfig(mlp_depth=2, skip_in=(), mlp_width=16,
                                              render_hidden=16, render_layers=1,
                                              sphere_clamp=not background))
        sampler = ErrorBoundSampler(ErrorBoundSamplerConfig(n_samples=8, n_samples_eval=16,
                                                            n_samples_extra=4))
        cfg = TrainConfig(steps=4, rays=32, sampler="error_bounded", anneal_rgb=2)
    if background:
        model.background = NeRFPlusPlusBackground(BackgroundConfig(
            n_samples=4, multires=2, n_layers=2, d_hidden=8, skip_in=(), feature_dim=4,
            multires_view=1, colour_hidden=4))
    t = Trainer(model, data, cfg, prior=prior, sampler=sampler)
    t.host_branch = False  # the NaN-safe update as on a GPU (on the CPU it reads a flag)
    return t


@pytest.mark.parametrize("background", [False, True])
@pytest.mark.parametrize("kind", ["fast", "paper"])
def test_train_step_has_no_sync(kind, background):
    t = _trainer(kind, background)
    for warm in (True, False):  # a warm-up step (smoothed target, sparsity) and a later one
        if not warm:
            t.step = t.cfg.anneal_rgb
        with SyncDetector() as det:
            terms = t.train_step()
        assert not det.calls, f"{kind}: sync points in a training step:\n{det.report()}"
    assert all(torch.isfinite(v) for v in terms.values())


def _syncs(fn) -> int:
    with SyncDetector() as det:
        fn()
    return len(det.calls)


def test_detector_sees_the_usual_sync_points():
    x = torch.randn(10)
    m = x > 0
    idx, i0 = torch.tensor([3]), torch.tensor(3)

    def setitem():
        x[m] = 0.0

    syncing = [lambda: x.sum().item(), lambda: bool(m.any()), lambda: float(x.sum()),
               lambda: x.tolist(), lambda: x.nonzero(), lambda: x[m], setitem,
               lambda: torch.unique(x), lambda: torch.where(m), lambda: x[i0],
               lambda: torch.tensor([1.0, 2.0]), lambda: torch.masked_select(x, m),
               lambda: torch.repeat_interleave(x, torch.full((10,), 2)),
               lambda: f"{x.sum()}", lambda: x.numpy()]
    for k, fn in enumerate(syncing):
        assert _syncs(fn) == 1, k
    free = [lambda: x[idx], lambda: torch.where(m, x, torch.zeros_like(x)),
            lambda: torch.repeat_interleave(x, 2), lambda: x.sum() * 2, lambda: m.any(),
            lambda: torch.randperm(10), lambda: x[1:3], lambda: x[None, 2]]
    for k, fn in enumerate(free):
        assert _syncs(fn) == 0, k
