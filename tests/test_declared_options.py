"""What the registered pieces declare they read (`svolsdf.registry.DeclaresOptions`): every
declared key is an option of the config, and a piece reads no option of its section beyond its
declaration (checked by building it on a config that records the options read)."""

from __future__ import annotations

import pytest
import torch

from svolsdf.config import preset
from svolsdf.field.kinds import FieldInputs, get_field_kind
from svolsdf.fusion.mesh_methods import get_mesh_method
from svolsdf.registry import DeclaresOptions
from svolsdf.render.sampler_registry import SamplerInputs, get_sampler


class _Recording:
    """``obj`` whose attribute reads are recorded (as ``prefix.name``) in ``seen``."""

    def __init__(self, obj, prefix: str, seen: set[str]):
        self._obj, self._prefix, self._seen = obj, prefix, seen

    def __getattr__(self, name):
        self._seen.add(f"{self._prefix}.{name}")
        return getattr(self._obj, name)


def _configs():
    for name in ("fast", "paper", "draft"):
        cfg = preset(name)
        yield cfg
        cfg = preset(name)
        cfg.field.init, cfg.field.background, cfg.mesh.tsdf.fill_holes = "sphere", True, 1.0
        yield cfg


@pytest.mark.parametrize("get, names", [
    (get_field_kind, ("grid", "mlp")), (get_sampler, ("mvs", "error_bounded")),
    (get_mesh_method, ("field", "poisson", "tsdf"))])
def test_every_declared_option_is_an_option_of_the_config(get, names):
    for name in names:
        entry = get(name)
        assert isinstance(entry, DeclaresOptions)
        for cfg in _configs():
            cfg.field.kind = name if get is get_field_kind else cfg.field.kind
            for key, value in entry.reads(cfg).items():
                assert value is not None or key.endswith("scale"), key


@pytest.mark.parametrize("kind", ["grid", "mlp"])
def test_a_field_kind_reads_no_field_option_it_does_not_declare(kind):
    for cfg in _configs():
        cfg.field.kind = kind
        if kind == "mlp":
            cfg.field.init, cfg.field.mlp_depth, cfg.field.mlp_width = "sphere", 5, 64
        entry = get_field_kind(kind)
        from_mvs = entry.starts_from_mvs and cfg.field.init == "mvs"
        seen: set[str] = set()
        f = _Recording(cfg.field, "field", seen)
        entry.build(FieldInputs(f, not from_mvs, lambda: torch.tensor([[-1.0] * 3, [1.0] * 3])))
        if entry.schedule is not None:
            entry.schedule(f, cfg.train, not from_mvs)
        if entry.check is not None:
            entry.check(f, cfg.train, not from_mvs)
        # kind and init choose the kind and its start; the rest must be declared
        assert seen - {"field.kind", "field.init"} <= set(entry.option_keys(cfg)), kind


@pytest.mark.parametrize("name", ["mvs", "error_bounded"])
def test_a_sampler_reads_no_train_option_it_does_not_declare(name):
    cfg = preset("fast")
    seen: set[str] = set()
    get_sampler(name)(SamplerInputs(_Recording(cfg.train, "train", seen), None, True))
    assert seen <= set(get_sampler(name).option_keys(cfg))
    assert get_sampler("mvs").reads(cfg) == {"train.samples_uniform": cfg.train.samples_uniform,
                                             "train.samples_fine": cfg.train.samples_fine}
