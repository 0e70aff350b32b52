"""The trainer asks the field what its training needs (`svolsdf.field.base.SurfaceModel`: its
parameter groups, per-step hooks and extra losses) and probes no attribute: a field written
here declares them and is trained as it declares."""

from __future__ import annotations

import ast
from pathlib import Path

import torch
from test_trainer import _data

import svolsdf
from svolsdf.config import TrainConfig
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig
from svolsdf.optimize.trainer import Trainer
from svolsdf.render.samplers import ErrorBoundSampler, ErrorBoundSamplerConfig


class _Declaring(VolSDFField):
    """A tiny VolSDF MLP whose colour network trains at its own rate, with a loss of its own
    and hooks that record when they run."""

    def __init__(self):
        super().__init__(VolSDFFieldConfig(mlp_depth=2, skip_in=(), mlp_width=16, render_hidden=16,
                                           render_layers=1))
        self.calls: list[tuple] = []

    def get_param_groups(self, train):
        colour = list(self.colour_parameters())
        ids = {id(p) for p in colour}
        rest = [p for p in self.parameters() if id(p) not in ids]
        return [{"params": rest, "lr": train.lr}, {"params": colour, "lr": 0.0}]

    def colour_parameters(self):
        return list(self.colour_net.parameters())

    def before_step(self):
        self.calls.append(("before_step",))

    def grow(self, resolution):
        self.calls.append(("grow", resolution))
        return False

    def extra_losses(self, train):
        yield "beta_pull", 0.5, (self.beta - 0.05) ** 2


def test_the_trainer_trains_the_field_as_it_declares():
    torch.manual_seed(0)
    model = _Declaring()
    colour_before = [p.detach().clone() for p in model.colour_parameters()]
    sampler = ErrorBoundSampler(ErrorBoundSamplerConfig(n_samples=8, n_samples_eval=16,
                                                        n_samples_extra=4))
    cfg = TrainConfig(mode="volsdf", steps=3, rays=16, sampler="error_bounded")
    t = Trainer(model, _data(), cfg, sampler=sampler, grid_schedule=[(1, 99)])
    assert [g["lr"] for g in t.optimizer.param_groups] == [cfg.lr, 0.0]
    terms = [t.train_step() for _ in range(3)]
    assert all("beta_pull" in s for s in terms)
    torch.testing.assert_close(terms[0]["total"] - terms[0]["rgb"] * cfg.rgb_weight
                               - terms[0]["eikonal"] * cfg.eikonal_weight,
                               0.5 * terms[0]["beta_pull"])
    assert model.calls == [("before_step",), ("grow", 99), ("before_step",), ("before_step",)]
    for p, q in zip(model.colour_parameters(), colour_before, strict=True):
        torch.testing.assert_close(p, q)  # (rate 0: its own group)


def test_the_trainer_and_the_builders_probe_no_attribute():
    root = Path(svolsdf.__file__).parent
    for module in ("optimize/trainer.py", "pipeline/builders.py", "render/guided.py",
                   "pipeline/mesh.py", "commands/render.py"):
        calls = [n.func.id for n in ast.walk(ast.parse((root / module).read_text()))
                 if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                 and n.func.id in ("hasattr", "getattr")]
        assert not calls, f"{module} probes with {calls}: ask the SurfaceModel interface"
