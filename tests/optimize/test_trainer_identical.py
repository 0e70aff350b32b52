"""What the trainer asks of the field it trains (its parameter groups, per-step hooks and extra
losses, `svolsdf.field.base.SurfaceModel`) gives the same training as ever: a few steps of the
fast preset's pieces (grid field from the sphere and from MVS, grown coarse to fine, the grid's
eikonal and smoothness terms, annealed beta, colour steps, a background) and of the paper's (the
VolSDF MLP with a beta floor), at a fixed seed, end at the losses and parameters recorded here."""

from __future__ import annotations

import pytest
import torch
from test_sync_free import _prior
from test_trainer import _data

from svolsdf.config import TrainConfig
from svolsdf.field.background import BackgroundConfig, NeRFPlusPlusBackground
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig
from svolsdf.optimize.trainer import Trainer
from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler
from svolsdf.render.samplers import ErrorBoundSampler, ErrorBoundSamplerConfig


def _background():
    return NeRFPlusPlusBackground(BackgroundConfig(
        n_samples=4, multires=2, n_layers=2, d_hidden=8, skip_in=(), feature_dim=4,
        multires_view=1, colour_hidden=4))


def _run(kind: str) -> tuple[list[float], list[float]]:
    """(the total loss of every step, the sum of each parameter at the end)."""
    torch.manual_seed(0)
    data = _data()
    data.focus = torch.zeros(3, data.images.shape[2], data.images.shape[3], dtype=torch.bool)
    data.focus[:, 4:14, 6:18] = True
    prior = _prior(data)
    schedule = None
    if kind.startswith("grid"):
        model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]),
                             GridFieldConfig(resolution=8, sphere_clamp_scale=None))
        model.background = _background()
        if kind == "grid-mvs":
            model.mvs_initialised = True  # (the start from the MVS surface's flag)
        sampler = MVSGuidedSampler(prior, GuidedSamplerConfig(samples_coarse=16, samples_uniform=8,
                                                              samples_fine=8))
        cfg = TrainConfig(steps=5, rays=32, beta_start=0.05, anneal_rgb=2, smooth_weight=0.1,
                          grid_eikonal_weight=0.1, colour_steps=2, colour_rays=16,
                          object_ray_fraction=0.5, prior_floor=1e-4)
        schedule = [(2, 12)]
    else:
        model = VolSDFField(VolSDFFieldConfig(mlp_depth=2, skip_in=(), mlp_width=16,
                                              render_hidden=16, render_layers=1))
        model.laplace.beta_min = 0.02
        sampler = ErrorBoundSampler(ErrorBoundSamplerConfig(n_samples=8, n_samples_eval=16,
                                                            n_samples_extra=4))
        cfg = TrainConfig(steps=4, rays=32, sampler="error_bounded", anneal_rgb=2)
    t = Trainer(model, data, cfg, prior=prior, sampler=sampler, grid_schedule=schedule)
    losses = []
    for _ in range(cfg.steps + cfg.colour_steps):
        losses.append(float(t.train_step()["total"]))
    return losses, [float(p.detach().double().sum()) for p in t.model.parameters()]


#: recorded by `_run` before the field declared its hooks (the trainer probed it then)
RECORDED = {
    "grid-sphere": (
        [3.328488826751709, 3.491891384124756, 3.756546974182129, 3.7099733352661133,
         3.9207253456115723, 0.2568431496620178, 0.23677733540534973],
        [418.2340156715363, -4.4623488788345185, -3.123077768784242, 25.7888454180867,
         3.7852085427184647, -0.5386777713720221, -0.11495327602460748, -0.4764121347106993,
         0.5211213214497548, -0.08126168698072433, 0.004451410379260778, 0.6229317591059953,
         0.37060829252004623, 1.6161926086060703, -0.8131531067192554, 0.6898159980773926,
         -0.4936069529503584, -1.143640961498022, -0.32605762407183647, 1.029856313019991,
         -0.39546269178390503],
    ),
    "grid-mvs": (
        [3.327425718307495, 3.5027172565460205, 3.775596857070923, 3.71744441986084,
         3.9026260375976562, 0.2568728029727936, 0.23669162392616272],
        [427.104548712261, -4.852736400290951, -2.5341140803893722, 25.693872080817698,
         3.7590935824628104, -0.5386024383478798, -0.04879731351684313, -0.4760786918923259,
         0.520069980469998, -0.08126159757375717, 0.004451410379260778, 0.6224636828992516,
         0.3706420660018921, 1.6165210588369519, -0.8131579179316759, 0.6896864362061024,
         -0.49360738694667816, -1.1433933414518833, -0.3259282670915127, 1.0300415009260178,
         -0.3953617811203003],
    ),
    "mlp": (
        [1.5658892393112183, 1.4974055290222168, 1.5725176334381104, 2.0902626514434814],
        [-0.017237523308722302, 7.9920919090509415, -3.2451159646952874, -0.026390483661089092,
         22.556351959705353, 1.0280275958357379, -154.19895339012146, 455.5148092508316,
         1822.0975775122643, -0.0016864542849361897, 9.18597936630249, 0.6701363737811334,
         0.09070170670747757, 1.9175620675086975, -1.0850925035774708, 0.10200309753417969],
    ),
}


@pytest.mark.parametrize("kind", ["grid-sphere", "grid-mvs", "mlp"])
def test_training_is_what_it_was(kind):
    losses, params = _run(kind)
    want_losses, want_params = RECORDED[kind]
    # the same computation: equal up to float32's last bits across machines and libraries
    torch.testing.assert_close(torch.tensor(losses, dtype=torch.float64),
                               torch.tensor(want_losses, dtype=torch.float64),
                               rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(torch.tensor(params, dtype=torch.float64),
                               torch.tensor(want_params, dtype=torch.float64),
                               rtol=1e-5, atol=1e-5)
